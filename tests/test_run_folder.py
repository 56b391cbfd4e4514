"""Run-folder ownership (dynslam_cli/run/folder.py): lock, refusal of a folder holding a run, --overwrite."""

import json
import os
import socket
import subprocess
import sys
import time

import pytest
from test_run_cli import TINY, _run, clip  # noqa: F401  (clip is a fixture)

from dynslam_cli.errors import DynslamError
from dynslam_cli.run.folder import LOCK_NAME, FolderLock, claim_folder, clear_run_folder

FAST = ["--mode", "static", "-q", "--set", "run.mesh=false"] + TINY


def snapshot(folder):
    """Every file under ``folder`` with its bytes."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def one_line_error(res, *parts):
    assert res.exit_code == 2, res.output
    lines = res.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:"), res.output
    for part in parts:
        assert part in lines[0], (part, lines[0])
    return lines[0]


@pytest.fixture
def completed(clip, tmp_path):  # noqa: F811
    """A completed run folder with an eval output, masks and a file of the user's."""
    out = tmp_path / "run"
    res = _run(["run", "--seq", str(clip), "--out", str(out)] + FAST)
    assert res.exit_code == 0, res.output
    (out / "ate.json").write_text('{"rmse_m": 0.123}\n')
    (out / "masks").mkdir()
    (out / "masks" / "1.000000.png").write_bytes(b"old mask")
    (out / "notes.txt").write_text("mine\n")
    return out


def write_lock(folder, pid, started_unix=None):
    folder.mkdir(parents=True, exist_ok=True)
    info = {"pid": pid, "host": socket.gethostname(), "token": "someone-else",
            "started_unix": time.time() if started_unix is None else started_unix, "started": "earlier"}
    (folder / LOCK_NAME).write_text(json.dumps(info) + "\n")


def test_new_run_into_completed_folder_is_refused_before_writing(clip, completed, monkeypatch):  # noqa: F811
    before = snapshot(completed)

    def boom(self, *a, **k):
        raise RuntimeError("this run would fail")

    monkeypatch.setattr("dynslam_cli.slam.system.SLAM.process", boom)
    res = _run(["run", "--seq", str(clip), "--out", str(completed), "--set", "mapping.iters=4"] + FAST)
    one_line_error(res, str(completed), "already holds a run", "completed", "synth/toybox", "--overwrite", "--resume")
    assert snapshot(completed) == before
    assert json.loads((completed / "run.json").read_text())["status"] == "completed"


def test_overwrite_clears_every_file_of_the_old_run_only(clip, completed):  # noqa: F811
    old_started = json.loads((completed / "run.json").read_text())["started"]
    (completed / ".ate.json.x1y2.json").write_text("{")  # a leftover of an interrupted atomic write
    time.sleep(1.1)  # run.json's start time has a resolution of 1 s
    res = _run(["run", "--seq", str(clip), "--out", str(completed), "--overwrite"] + FAST)
    assert res.exit_code == 0, res.output
    assert not (completed / "ate.json").exists() and not (completed / ".ate.json.x1y2.json").exists()
    assert not (completed / "masks").exists()
    assert (completed / "notes.txt").read_text() == "mine\n"
    meta = json.loads((completed / "run.json").read_text())
    assert meta["status"] == "completed" and meta["started"] != old_started
    assert (completed / "traj_est.txt").is_file() and not (completed / LOCK_NAME).exists()


def test_resume_and_overwrite_together_are_refused(clip, completed):  # noqa: F811
    before = snapshot(completed)
    res = _run(["run", "--seq", str(clip), "--out", str(completed), "--overwrite", "--resume"] + FAST)
    one_line_error(res, "--resume and --overwrite exclude each other")
    assert snapshot(completed) == before


def test_folder_locked_by_a_live_pid_is_refused(clip, tmp_path):  # noqa: F811
    out = tmp_path / "busy"
    holder = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        write_lock(out, holder.pid)
        (out / "run.json").write_text('{"status": "running"}\n')
        before = snapshot(out)
        res = _run(["run", "--seq", str(clip), "--out", str(out), "--overwrite"] + FAST)
        one_line_error(res, str(out), "in use by another run", f"pid {holder.pid}")
        assert snapshot(out) == before
    finally:
        holder.kill()
        holder.wait()


def test_stale_lock_is_taken_over_with_a_warning(clip, tmp_path):  # noqa: F811
    out = tmp_path / "stale"
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    write_lock(out, gone.pid)
    res = _run(["run", "--seq", str(clip), "--out", str(out)] + FAST)
    assert res.exit_code == 0, res.output
    warnings = [ln for ln in res.stderr.splitlines() if ln.startswith("warning:")]
    assert len(warnings) == 1 and "taking over" in warnings[0] and f"pid {gone.pid}" in warnings[0]
    assert json.loads((out / "run.json").read_text())["status"] == "completed"
    assert not (out / LOCK_NAME).exists()


def test_lock_is_exclusive_and_released(tmp_path):
    folder = tmp_path / "f"
    with FolderLock(folder):
        assert (folder / LOCK_NAME).is_file()
        with pytest.raises(DynslamError, match=f"in use by another run \\(pid {os.getpid()},"):
            FolderLock(folder).acquire()
    assert not (folder / LOCK_NAME).exists()
    with pytest.raises(ValueError, match="boom"):
        with FolderLock(folder):
            raise ValueError("boom")
    assert not (folder / LOCK_NAME).exists()


def test_lock_of_a_reused_pid_is_stale(tmp_path, capsys):
    # this process is alive but started long after the lock was written: its pid was reused
    write_lock(tmp_path, os.getpid(), started_unix=1.0)
    with FolderLock(tmp_path) as lock:
        assert json.loads((tmp_path / LOCK_NAME).read_text())["token"] == lock.token
    assert "taking over" in capsys.readouterr().err


def test_lock_of_another_host_is_never_taken(tmp_path):
    (tmp_path / LOCK_NAME).write_text(json.dumps({"pid": 1, "host": "elsewhere", "started": "then"}))
    with pytest.raises(DynslamError, match="pid 1 on host elsewhere .* delete"):
        FolderLock(tmp_path).acquire()
    assert (tmp_path / LOCK_NAME).is_file()


def test_a_file_as_the_run_folder(tmp_path):
    (tmp_path / "f").write_text("x")
    with pytest.raises(DynslamError, match="is a file, not a folder"):
        FolderLock(tmp_path / "f").acquire()


def test_clear_keeps_unknown_files(tmp_path):
    for name in ("run.json", "ate.png", "montage.png", "checkpoint.pt", "notes.txt", "cell.json", ".run.json.ab.json"):
        (tmp_path / name).write_text("x")
    (tmp_path / "renders").mkdir()
    (tmp_path / "renders" / "1_depth.png").write_text("x")
    (tmp_path / "mine").mkdir()
    gone = clear_run_folder(tmp_path)
    assert sorted(gone) == sorted([".run.json.ab.json", "ate.png", "checkpoint.pt", "montage.png", "renders", "run.json"])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cell.json", "mine", "notes.txt"]


def test_claim_of_a_folder_with_eval_outputs_only(tmp_path):
    (tmp_path / "ate.json").write_text("{}")
    with pytest.raises(DynslamError, match="already holds a run \\(files ate.json\\)"):
        claim_folder(tmp_path)
    assert claim_folder(tmp_path, overwrite=True) == ["ate.json"]
    assert claim_folder(tmp_path) == []
