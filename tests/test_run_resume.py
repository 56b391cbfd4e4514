"""--resume continues only the checkpoint's own sequence, config and code version."""

import json

import pytest
from test_run_cli import TINY, _run, clip  # noqa: F401  (clip is a fixture)
from test_run_folder import one_line_error, snapshot

from dynslam_cli.slam.toyscene import write_sequence

ARGS = ["--mode", "static", "-q", "--set", "run.mesh=false"] + TINY


@pytest.fixture
def partial(clip, tmp_path):  # noqa: F811
    """A run stopped after 3 of 6 frames: checkpoint.pt, run.json interrupted."""
    out = tmp_path / "part"
    res = _run(["run", "--seq", str(clip), "--out", str(out), "--stop-after", "3"] + ARGS)
    assert res.exit_code == 0, res.output
    assert json.loads((out / "run.json").read_text())["status"] == "interrupted"
    return out


def test_resume_with_another_sequence_is_refused(partial, tmp_path):
    other = write_sequence(tmp_path / "clips" / "other", n=6, width=80, height=60, step=0.02)
    before = snapshot(partial)
    res = _run(["run", "--seq", str(other), "--out", str(partial), "--resume"] + ARGS)
    one_line_error(res, f"sequence {other} differs (old synth/toybox, new synth/other)", str(partial))
    assert snapshot(partial) == before


def test_resume_with_another_cut_is_refused(clip, partial):  # noqa: F811
    before = snapshot(partial)
    res = _run(["run", "--seq", str(clip), "--out", str(partial), "--resume", "--frames", "5"] + ARGS)
    one_line_error(res, "differs (old 6 frames", "new 5 frames")
    assert snapshot(partial) == before


def test_resume_with_a_changed_config_key_names_it(clip, partial):  # noqa: F811
    before = snapshot(partial)
    res = _run(["run", "--seq", str(clip), "--out", str(partial), "--resume"] + ARGS + ["--set", "tracking.iters=4"])
    one_line_error(res, "config key tracking.iters differs (old 3, new 4)", "--overwrite")
    assert snapshot(partial) == before
    # --stop-after only says when a call stops: it may differ; the run then completes
    res = _run(["run", "--seq", str(clip), "--out", str(partial), "--resume"] + ARGS)
    assert res.exit_code == 0, res.output
    assert json.loads((partial / "run.json").read_text())["status"] == "completed"
    assert not (partial / "checkpoint.pt").exists()


def test_resume_of_a_completed_run_is_refused(clip, tmp_path):  # noqa: F811
    out = tmp_path / "done"
    args = ["run", "--seq", str(clip), "--out", str(out), "--set", "run.keep_checkpoint=true",
            "--set", "run.checkpoint_every=2"] + ARGS
    assert _run(args).exit_code == 0
    assert (out / "checkpoint.pt").is_file()
    before = snapshot(out)
    one_line_error(_run(args + ["--resume"]), "is completed, nothing to resume")
    assert snapshot(out) == before


def test_checkpoint_of_an_older_version_is_refused(clip, partial):  # noqa: F811
    import torch

    state = torch.load(partial / "checkpoint.pt", weights_only=False)
    del state["identity"]
    torch.save(state, partial / "checkpoint.pt")
    before = snapshot(partial)
    res = _run(["run", "--seq", str(clip), "--out", str(partial), "--resume"] + ARGS)
    one_line_error(res, "written by an older dynslam", "--overwrite")
    assert snapshot(partial) == before


def test_resume_after_a_code_change_is_refused(clip, partial, monkeypatch):  # noqa: F811
    from dynslam_cli.run import checkpoint

    monkeypatch.setattr(checkpoint, "code_version", lambda: "9.9.9+git.abc")
    before = snapshot(partial)
    res = _run(["run", "--seq", str(clip), "--out", str(partial), "--resume"] + ARGS)
    one_line_error(res, "code version differs (old ", "new 9.9.9+git.abc)")
    assert snapshot(partial) == before
