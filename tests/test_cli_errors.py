"""Output that cannot be written is one line naming the path and the reason (exit 2), never a
traceback; earlier files stay as they were and `synth` leaves no temporary folder behind.

Tests run as root here, which ignores permission bits: a read-only folder is simulated where the
operating system would refuse (mkstemp or rename raising PermissionError / EROFS), and real
refusals come from a path through a regular file (NotADirectoryError, FileExistsError) or a target
that is a folder (IsADirectoryError)."""

from __future__ import annotations

import errno
import json
import os
from pathlib import Path

import pytest
from typer.testing import CliRunner

from dynslam_cli.cli import app
from dynslam_cli.utils import io

runner = CliRunner()
SYNTH = ["--frames", "2", "--size", "32x24", "-q"]


def cli_error(args, *fragments) -> str:
    res = runner.invoke(app, args)
    assert res.exit_code == 2, res.output
    assert "Traceback" not in res.output
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), res.output
    for frag in fragments:
        assert frag in lines[0], (frag, lines[0])
    return lines[0]


def snapshot(folder: Path) -> dict:
    """Every file below ``folder`` (hidden ones too) with its bytes."""
    return {str(p.relative_to(folder)): (p.read_bytes() if p.is_file() else None)
            for p in sorted(folder.rglob("*"))}


def refuse_in(monkeypatch, folder: Path, err: int = errno.EACCES) -> None:
    """Make ``folder`` behave like a read-only one for new files and renames."""
    real_mkstemp, real_replace = io.tempfile.mkstemp, os.replace

    def mkstemp(*args, dir=None, **kw):  # noqa: A002
        if dir is not None and Path(dir) == folder:
            raise OSError(err, os.strerror(err), os.path.join(dir, ".tmp"))
        return real_mkstemp(*args, dir=dir, **kw)

    def replace(src, dst):
        if Path(dst).parent == folder or Path(src) == folder:
            raise OSError(err, os.strerror(err), str(src), None, str(dst))
        return real_replace(src, dst)

    monkeypatch.setattr(io.tempfile, "mkstemp", mkstemp)
    monkeypatch.setattr(os, "replace", replace)


@pytest.fixture
def blocker(tmp_path: Path) -> Path:
    f = tmp_path / "afile"
    f.write_text("keep me")
    return f


# ------------------------------------------------------------------------------------- synth
def test_synth_out_through_a_file(tmp_path: Path, blocker: Path):
    before = snapshot(tmp_path)
    cli_error(["synth", "static", "--out", str(blocker / "scene")] + SYNTH, str(blocker), "File exists")
    assert snapshot(tmp_path) == before


def test_synth_failures_leave_the_earlier_scene_and_no_temp_folder(tmp_path: Path, monkeypatch):
    out = tmp_path / "scene"
    res = runner.invoke(app, ["synth", "static", "--out", str(out)] + SYNTH)
    assert res.exit_code == 0, res.output
    before = snapshot(tmp_path)
    # the scene folder cannot be moved aside (renaming a read-only folder needs write permission on it)
    real_replace = os.replace

    def replace(src, dst):
        if Path(src) == out:
            raise PermissionError(errno.EACCES, "Permission denied", str(src), None, str(dst))
        return real_replace(src, dst)

    monkeypatch.setattr(os, "replace", replace)
    cli_error(["synth", "static", "--out", str(out), "--seed", "1"] + SYNTH, str(out), "Permission denied")
    assert snapshot(tmp_path) == before
    monkeypatch.undo()
    # the disk fills up half-way through writing the lists
    import dynslam_cli.synth.render as render

    def full(*a, **k):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(out / "rgb.txt"))

    monkeypatch.setattr(render, "_write_lists", full)
    cli_error(["synth", "static", "--out", str(out), "--seed", "1"] + SYNTH, "rgb.txt", "No space left on device")
    assert snapshot(tmp_path) == before


# --------------------------------------------------------------------------------------- run
def test_run_out_through_a_file(tmp_path: Path, blocker: Path):
    from dynslam_cli.slam.toyscene import write_sequence

    seq = write_sequence(tmp_path / "toy", n=2, width=32, height=24)
    before = snapshot(tmp_path)
    cli_error(["run", "--seq", str(seq), "--mode", "static", "--out", str(blocker / "run"), "-q"],
              str(blocker / "run"), "Not a directory")
    assert snapshot(tmp_path) == before


def test_run_read_only_out(tmp_path: Path, monkeypatch):
    from dynslam_cli.slam.toyscene import write_sequence

    seq = write_sequence(tmp_path / "toy", n=2, width=32, height=24)
    out = tmp_path / "run"
    out.mkdir()
    before = snapshot(tmp_path)
    refuse_in(monkeypatch, out, errno.EROFS)
    cli_error(["run", "--seq", str(seq), "--mode", "static", "--out", str(out), "-q"],
              str(out / "config.yaml"), "Read-only file system")
    assert snapshot(tmp_path) == before


# ---------------------------------------------------------------------------- eval and tables
@pytest.fixture
def run_dir(tmp_path: Path) -> Path:
    """A completed run folder whose estimate is the ground truth (no SLAM needed)."""
    from dynslam_cli.slam.toyscene import write_sequence

    seq = write_sequence(tmp_path / "toy", n=4, width=32, height=24)
    run = tmp_path / "results" / "runs" / "synth" / "toy" / "static"
    run.mkdir(parents=True)
    (run / "traj_est.txt").write_text((seq / "groundtruth.txt").read_text())
    (run / "run.json").write_text(json.dumps({
        "status": "completed", "mode": "static", "variant": "static", "frames": 4,
        "sequence": {"spec": str(seq), "dataset": "synth", "name": "toy", "path": str(seq),
                     "groundtruth": str(seq / "groundtruth.txt")}}))
    return run


def test_eval_ate_target_is_a_folder_or_read_only(run_dir: Path, monkeypatch):
    (run_dir / "ate.json").mkdir()
    before = snapshot(run_dir)
    cli_error(["eval-ate", str(run_dir)], str(run_dir / "ate.json"), "Is a directory")
    assert snapshot(run_dir) == before
    (run_dir / "ate.json").rmdir()
    (run_dir / "ate.json").write_text("{}\n")
    before = snapshot(run_dir)
    refuse_in(monkeypatch, run_dir)
    cli_error(["eval-ate", str(run_dir)], str(run_dir / "ate"), "Permission denied")
    assert snapshot(run_dir) == before


def test_tables_out_unwritable(run_dir: Path, blocker: Path, monkeypatch):
    results = run_dir.parents[3]
    before = snapshot(blocker.parent)
    cli_error(["tables", "--results", str(results), "--out", str(blocker / "t"), "--no-plots"],
              str(blocker / "t"), "Not a directory")
    assert snapshot(blocker.parent) == before
    out = results / "tables"
    out.mkdir()
    refuse_in(monkeypatch, out, errno.ENOSPC)
    cli_error(["tables", "--results", str(results), "--out", str(out), "--no-plots"],
              str(out), "No space left on device")
    assert snapshot(blocker.parent) == before | {str(out.relative_to(blocker.parent)): None}


def test_os_error_line_without_a_path():
    from dynslam_cli.cli import os_error_line

    assert os_error_line(OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))) == "No space left on device"
    assert os_error_line(OSError("device gone")) == "OSError: device gone"
    line = os_error_line(OSError(errno.EXDEV, os.strerror(errno.EXDEV), "/a", None, "/b"))
    assert line == "file system error at /a -> /b: Invalid cross-device link"
