"""benchmarks/_bench.py: a completed run is reused only for the config and code that made it."""

import json

import pytest
from benchmark_scripts import load

from dynslam_cli.config.loader import save_config
from dynslam_cli.config.resolve import resolve_config
from dynslam_cli.run.checkpoint import code_version

bench = load("_bench")

SETS = ["synth.width=64", "synth.height=48", "synth.frames=3"]


def _completed(out, cfg, code=None):
    """A run folder as run_sequence leaves it: config.yaml and a completed run.json (returned)."""
    out.mkdir(parents=True, exist_ok=True)
    save_config(cfg, out / "config.yaml")
    meta = {"status": "completed", "versions": {"dynslam": code or code_version()}}
    (out / "run.json").write_text(json.dumps(meta))
    return meta


class TestStaleRun:
    def test_the_same_config_and_code_stand(self, tmp_path):
        cfg = resolve_config("synth/walker", None, SETS)
        meta = _completed(tmp_path, cfg)
        assert bench.stale_run(tmp_path, cfg, meta) is None
        # where files live is not what a run computes
        elsewhere = resolve_config("synth/walker", None, SETS + ["data.root=/elsewhere"])
        assert bench.stale_run(tmp_path, elsewhere, meta) is None

    def test_another_seed_or_code_does_not(self, tmp_path):
        cfg = resolve_config("synth/walker", None, SETS)
        meta = _completed(tmp_path, cfg)
        why = bench.stale_run(tmp_path, resolve_config("synth/walker", None, SETS + ["run.seed=2"]), meta)
        assert why == "config key run.seed differs (there 0, asked 2)"
        meta = _completed(tmp_path, cfg, code="0.0.1+git.0000000")
        assert bench.stale_run(tmp_path, cfg, meta).startswith("code version differs (there 0.0.1+git.0000000")

    def test_an_unreadable_config_does_not(self, tmp_path):
        cfg = resolve_config("synth/walker", None, SETS)
        meta = _completed(tmp_path, cfg)
        (tmp_path / "config.yaml").write_text("run:\n  no_such_key: 1\n")
        assert bench.stale_run(tmp_path, cfg, meta).startswith("its config.yaml does not read")
        (tmp_path / "config.yaml").unlink()
        assert bench.stale_run(tmp_path, cfg, meta).startswith("its config.yaml does not read")


class TestRunOrReuse:
    @pytest.fixture
    def runs(self, monkeypatch):
        """run_sequence replaced by one that records its calls and leaves a completed run folder."""
        import dynslam_cli.run.runner as runner

        calls = []

        def fake(spec, cfg, out_dir=None, overwrite=False, progress=True):
            calls.append(cfg.run.seed)
            _completed(out_dir, cfg)

        monkeypatch.setattr(runner, "run_sequence", fake)
        return calls

    def test_reuses_only_what_was_asked_for(self, tmp_path, runs, capsys):
        out = tmp_path / "run"
        bench.run_or_reuse("synth/walker", SETS, out, fresh=False)
        bench.run_or_reuse("synth/walker", SETS, out, fresh=False)  # the same: reused
        assert runs == [0]
        bench.run_or_reuse("synth/walker", SETS + ["run.seed=2"], out, fresh=False)  # another seed: run again
        assert runs == [0, 2]
        assert f"redoing {out}: config key run.seed differs (there 0, asked 2)" in capsys.readouterr().err
        bench.run_or_reuse("synth/walker", SETS + ["run.seed=2"], out, fresh=True)  # --fresh: always
        assert runs == [0, 2, 2]
