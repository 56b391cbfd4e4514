"""Run-folder ownership: one run at a time per folder, and never two runs' files mixed.

* **Lock**: ``<folder>/.lock`` (JSON: pid, host, start time, a token) is created with
  ``O_CREAT|O_EXCL``; a second writer gets a one-line :class:`DynslamError` naming the folder and the
  pid holding it.  A stale lock (its pid is no longer alive on this host, or the pid now belongs to
  a process started after the lock was written) is taken over with a one-line warning on stderr.
  A lock from another host is never judged stale: the message says which file to delete.
* **Claim** (:func:`claim_folder`, with the lock held, before anything is written): a folder that
  holds a run (any of :data:`RUN_FILES`, :data:`EVAL_FILES`, :data:`RUN_DIRS`) is refused unless
  ``overwrite`` (those entries are deleted, nothing else) or ``resume`` (a checkpoint.pt of a run
  that is not completed must be there).
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import sys
import time
import uuid
from datetime import datetime, timezone
from pathlib import Path
from typing import Optional

from dynslam_cli.errors import DynslamError

LOCK_NAME = ".lock"
# What a run writes (DEVELOPING.md, "Run folder"); the eval commands add EVAL_FILES.
RUN_FILES = ("run.json", "config.yaml", "checkpoint.pt", "traj_est.txt", "traj_unsmoothed.txt", "traj_online.txt",
             "mesh.ply", "timing.json", "classifier_updates.jsonl", "tracking_events.json", "frames.jsonl")
EVAL_FILES = ("ate.json", "ate.png", "ate_online.json", "ate_online.png", "mesh_metrics.json", "mask_metrics.json",
              "montage.png", "recording.rrd", "report.md", "demo_report.json")
RUN_DIRS = ("masks", "renders")
KNOWN = RUN_FILES + EVAL_FILES + RUN_DIRS
# A lock file that cannot be parsed (a writer killed between creating and filling it) older than this is stale.
UNREADABLE_STALE_S = 30.0


def _warn(msg: str) -> None:
    print(f"warning: {msg}", file=sys.stderr, flush=True)


def pid_alive(pid: int) -> bool:
    """Whether a process with this pid exists on this host (a pid we may not signal exists)."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _process_start(pid: int) -> Optional[float]:
    """Unix time at which process ``pid`` started (Linux /proc), or None when unknown."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        ticks = int(stat.rsplit(")", 1)[1].split()[19])  # field 22: starttime in clock ticks after boot
        btime = next(int(ln.split()[1]) for ln in Path("/proc/stat").read_text().splitlines()
                     if ln.startswith("btime "))
        return btime + ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, StopIteration):
        return None


def _holder_alive(info: dict) -> bool:
    pid = int(info.get("pid", -1))
    if not pid_alive(pid):
        return False
    started, proc = info.get("started_unix"), _process_start(pid)
    # the pid was reused: that process started after the lock was written (2 s for /proc's rounding)
    return not (isinstance(started, (int, float)) and proc is not None and proc > started + 2.0)


class FolderLock:
    """``with FolderLock(folder):`` owns ``folder`` (created if missing) until the block ends."""

    def __init__(self, folder: Path):
        self.folder = Path(folder)
        self.path = self.folder / LOCK_NAME
        self.token = uuid.uuid4().hex
        self.held = False

    def __enter__(self) -> "FolderLock":
        self.acquire()
        return self

    def __exit__(self, *exc) -> None:
        self.release()

    def _content(self) -> bytes:
        now = time.time()
        info = {"pid": os.getpid(), "host": socket.gethostname(), "token": self.token, "started_unix": now,
                "started": datetime.fromtimestamp(now, timezone.utc).isoformat(timespec="seconds")}
        return (json.dumps(info) + "\n").encode()

    def acquire(self) -> None:
        if self.folder.exists() and not self.folder.is_dir():
            raise DynslamError(f"run folder {self.folder} is a file, not a folder")
        self.folder.mkdir(parents=True, exist_ok=True)
        for _ in range(50):
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                self._judge_existing()
                continue
            try:
                os.write(fd, self._content())
            finally:
                os.close(fd)
            self.held = True
            return
        raise DynslamError(f"cannot lock run folder {self.folder}: {self.path} keeps reappearing")

    def _judge_existing(self) -> None:
        """Raise when the existing lock is held; take it over (and return) when it is stale."""
        raw, info = b"", None
        for _ in range(5):  # a writer fills its lock right after creating it
            try:
                raw = self.path.read_bytes()
            except FileNotFoundError:
                return  # released meanwhile: try again
            try:
                info = json.loads(raw.decode())
                break
            except (UnicodeDecodeError, ValueError):
                time.sleep(0.05)
        if not isinstance(info, dict) or "pid" not in info:
            try:
                age = time.time() - self.path.stat().st_mtime
            except FileNotFoundError:
                return
            if age < UNREADABLE_STALE_S:
                raise DynslamError(f"run folder {self.folder} is being locked by another run ({self.path} is "
                                   f"not readable yet); try again, or delete it if no run is using the folder")
            self._take_over(raw, f"an unreadable lock {self.path}")
            return
        pid, host, since = info.get("pid"), info.get("host", "?"), info.get("started", "?")
        if host != socket.gethostname():
            raise DynslamError(f"run folder {self.folder} is in use by pid {pid} on host {host} (since {since}); "
                               f"if no run is using it, delete {self.path}")
        if _holder_alive(info):
            raise DynslamError(f"run folder {self.folder} is in use by another run (pid {pid}, since {since}); "
                               f"wait for it to end or choose another --out")
        self._take_over(raw, f"a stale lock of pid {pid} (no longer running, since {since})")

    def _take_over(self, raw: bytes, what: str) -> None:
        """Move the stale lock aside; put it back if another process replaced it in between."""
        aside = self.folder / f"{LOCK_NAME}.stale-{os.getpid()}-{self.token[:8]}"
        try:
            os.rename(self.path, aside)
        except FileNotFoundError:
            return
        try:
            if aside.read_bytes() != raw:  # someone took it over first: that lock is live, restore it
                try:
                    os.link(aside, self.path)
                except OSError:
                    pass
                return
            _warn(f"taking over run folder {self.folder} from {what}")
        finally:
            aside.unlink(missing_ok=True)

    def release(self) -> None:
        """Remove the lock if it is still ours (every exit path of the owner calls this)."""
        if not self.held:
            return
        self.held = False
        try:
            info = json.loads(self.path.read_text())
        except (OSError, ValueError):
            return
        if isinstance(info, dict) and info.get("token") == self.token:
            self.path.unlink(missing_ok=True)


def run_entries(folder: Path) -> list[str]:
    """The known run-folder entries present in ``folder`` (in :data:`KNOWN` order)."""
    folder = Path(folder)
    return [name for name in KNOWN if (folder / name).exists() or (folder / name).is_symlink()]


def read_status(folder: Path) -> Optional[dict]:
    """run.json of ``folder`` as a dict, or None when absent or unreadable."""
    try:
        d = json.loads((Path(folder) / "run.json").read_text())
    except (OSError, ValueError):
        return None
    return d if isinstance(d, dict) else None


def describe_run(folder: Path, entries: list[str]) -> str:
    meta = read_status(folder)
    if meta is None:
        return "files " + ", ".join(entries)
    seq = meta.get("sequence") or {}
    name = f"{seq.get('dataset', '?')}/{seq.get('name', '?')}" if isinstance(seq, dict) else "?"
    return f"run.json says {meta.get('status', '?')}, sequence {name}"


def clear_run_folder(folder: Path) -> list[str]:
    """Delete every known run-folder entry (and temporary files of interrupted atomic writes of
    them); files the folder holds besides those are kept.  Returns the names deleted."""
    folder = Path(folder)
    gone = []
    for p in sorted(folder.iterdir()):
        name = p.name
        leftover = any(name.startswith(f".{k}.") for k in RUN_FILES + EVAL_FILES)  # utils.io temp names
        if name not in KNOWN and not leftover:
            continue
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        else:
            p.unlink()
        gone.append(name)
    return gone


def claim_folder(folder: Path, resume: bool = False, overwrite: bool = False) -> list[str]:
    """Check that a run may write into ``folder`` (call with the lock held, before writing anything).

    A new run needs a folder without a run in it, or ``overwrite`` (the old run's entries are
    deleted and their names returned).  ``resume`` needs a checkpoint.pt of a run that is not
    completed; eval outputs of the unfinished run, if any, are deleted.
    """
    folder = Path(folder)
    if resume and overwrite:
        raise DynslamError("--resume and --overwrite exclude each other: continue the run in "
                           f"{folder} or replace it, not both")
    entries = run_entries(folder)
    if resume:
        meta = read_status(folder) or {}
        if meta.get("status") == "completed":
            raise DynslamError(f"--resume: the run in {folder} is completed, nothing to resume "
                               f"(use --overwrite to run it again)")
        if not (folder / "checkpoint.pt").is_file():
            said = f" (run.json says {meta['status']})" if meta.get("status") else ""
            raise DynslamError(f"--resume: no checkpoint.pt in {folder}{said}; start again with --overwrite")
        stale = [folder / n for n in EVAL_FILES if (folder / n).exists()]
        for p in stale:
            p.unlink()
        return [p.name for p in stale]
    if not entries:
        return []
    if not overwrite:
        raise DynslamError(f"run folder {folder} already holds a run ({describe_run(folder, entries)}); "
                           f"use --overwrite to replace it (deletes its files) or --resume to continue it")
    return clear_run_folder(folder)
