"""Atomic file output: write to a temporary name beside the target, then rename.

A crash or an error half-way never leaves a truncated result file, and a file that already
existed stays intact until the new one is complete.  New files get the mode an ordinary
``open(..., "w")`` would give them (0666 less the umask); a file that is replaced keeps its mode.
An OS error (read-only folder, full disk, a path through a file) names the target, not the
temporary file.
"""

from __future__ import annotations

import contextlib
import json
import os
import stat
import tempfile
import threading
from pathlib import Path
from typing import Any, Iterator

_UMASK_LOCK = threading.Lock()


def proc_status(key: str) -> str | None:
    """The first word of line ``key`` of Linux's /proc/self/status (e.g. ``Umask``, ``VmHWM`` in kB);
    None where there is no such file or line."""
    try:
        with open("/proc/self/status", encoding="ascii", errors="replace") as f:
            for line in f:
                if line.startswith(key + ":"):
                    return line.split()[1]
    except (OSError, IndexError):
        pass
    return None


def current_umask() -> int:
    """The process umask, read without changing it where the system allows (Linux /proc)."""
    text = proc_status("Umask")
    if text is not None:
        with contextlib.suppress(ValueError):
            return int(text, 8)
    with _UMASK_LOCK:  # os.umask can only be read by setting it: set it straight back
        mask = os.umask(0o022)
        os.umask(mask)
    return mask


def default_mode(folder: bool = False) -> int:
    """Mode of a new file (0666) or folder (0777) under the current umask."""
    return (0o777 if folder else 0o666) & ~current_umask()


def _with_path(exc: OSError, path: Path) -> OSError:
    """The same OS error (same class by errno) naming ``path``."""
    if exc.errno is None:
        return exc
    return OSError(exc.errno, exc.strerror or os.strerror(exc.errno), str(path))


@contextlib.contextmanager
def atomic_path(target: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path in the target's folder; rename it onto ``target`` on success.

    ``suffix`` defaults to the target's suffix so that libraries choosing a format from the
    extension (trimesh, cv2, matplotlib) keep working.
    """
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    try:
        fd, tmp = tempfile.mkstemp(
            prefix=f".{target.name}.", suffix=target.suffix if suffix is None else suffix,
            dir=target.parent,
        )
    except OSError as exc:
        raise _with_path(exc, target) from exc
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        try:
            old = target.stat(follow_symlinks=True)
            mode = stat.S_IMODE(old.st_mode) if stat.S_ISREG(old.st_mode) else default_mode()
        except OSError:
            mode = default_mode()
        try:
            os.chmod(tmp_path, mode)
            os.replace(tmp_path, target)
        except OSError as exc:
            raise _with_path(exc, target) from exc
    except OSError as exc:
        if exc.filename == str(tmp_path):  # writing the temporary file failed (disk full, ...)
            raise _with_path(exc, target) from exc
        raise
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def write_bytes_atomic(target: str | os.PathLike, data: bytes) -> Path:
    with atomic_path(target) as tmp:
        tmp.write_bytes(data)
    return Path(target)


def write_text_atomic(target: str | os.PathLike, text: str) -> Path:
    return write_bytes_atomic(target, text.encode("utf-8"))


def write_json_atomic(target: str | os.PathLike, obj: Any, indent: int = 2) -> Path:
    return write_text_atomic(target, json.dumps(obj, indent=indent, sort_keys=False) + "\n")


def write_jsonl_atomic(target: str | os.PathLike, rows) -> Path:
    """One JSON line per item of ``rows`` (JSON Lines)."""
    return write_text_atomic(target, "".join(json.dumps(r) + "\n" for r in rows))
