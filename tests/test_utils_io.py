"""Atomic writes: new files honour the umask, replaced files keep their mode, OS errors name the target."""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path

import pytest

from dynslam_cli.utils import io


@pytest.fixture
def umask():
    """Set the umask for one test (restored afterwards)."""
    old = os.umask(0o022)
    os.umask(old)

    def set_(mask: int) -> None:
        os.umask(mask)

    yield set_
    os.umask(old)


def _mode(p: Path) -> int:
    return stat.S_IMODE(p.stat().st_mode)


@pytest.mark.parametrize("mask, expected", [(0o022, 0o644), (0o002, 0o664), (0o077, 0o600)])
def test_new_files_honour_the_umask(tmp_path: Path, umask, mask, expected):
    umask(mask)
    assert io.current_umask() == mask
    assert io.default_mode() == expected and io.default_mode(folder=True) == 0o777 & ~mask
    io.write_text_atomic(tmp_path / "a.txt", "x")
    io.write_json_atomic(tmp_path / "sub" / "b.json", {"k": 1})
    with io.atomic_path(tmp_path / "c.png") as tmp:
        tmp.write_bytes(b"png")
    for name in ("a.txt", "sub/b.json", "c.png"):
        assert _mode(tmp_path / name) == expected, name
    # compare with what an ordinary open() gives
    plain = tmp_path / "plain.txt"
    plain.write_text("x")
    assert _mode(plain) == expected
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt", "c.png", "plain.txt", "sub"]


def test_replaced_file_keeps_its_mode(tmp_path: Path, umask):
    umask(0o022)
    target = tmp_path / "a.txt"
    target.write_text("old")
    os.chmod(target, 0o640)
    io.write_text_atomic(target, "new")
    assert target.read_text() == "new" and _mode(target) == 0o640


def test_umask_read_does_not_change_it(umask):
    umask(0o027)
    assert io.current_umask() == 0o027
    assert io.current_umask() == 0o027
    assert os.umask(0o027) == 0o027


def test_failed_rename_names_the_target_and_leaves_no_temp(tmp_path: Path, monkeypatch):
    target = tmp_path / "r.json"
    target.write_text("earlier")

    def refuse(src, dst):
        raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(src), None, str(dst))

    monkeypatch.setattr(io.os, "replace", refuse)
    with pytest.raises(OSError) as info:
        io.write_json_atomic(target, {"new": 1})
    assert info.value.errno == errno.EROFS and info.value.filename == str(target)
    assert target.read_text() == "earlier"
    assert [p.name for p in tmp_path.iterdir()] == ["r.json"]


def test_failed_temp_write_names_the_target(tmp_path: Path):
    target = tmp_path / "big.bin"
    with pytest.raises(OSError) as info:
        with io.atomic_path(target) as tmp:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(tmp))
    assert isinstance(info.value, OSError) and info.value.errno == errno.ENOSPC
    assert info.value.filename == str(target)
    assert list(tmp_path.iterdir()) == []


def test_uncreatable_folder_and_temp(tmp_path: Path, monkeypatch):
    blocker = tmp_path / "afile"
    blocker.write_text("keep")
    with pytest.raises(NotADirectoryError):
        io.write_text_atomic(blocker / "sub" / "x.txt", "x")
    with pytest.raises(FileExistsError):
        io.write_text_atomic(blocker / "x.txt", "x")

    def denied(*a, dir=None, **k):  # noqa: A002 - what mkstemp raises in a folder without write permission
        raise PermissionError(errno.EACCES, "Permission denied", os.path.join(dir, ".x.tmp"))

    monkeypatch.setattr(io.tempfile, "mkstemp", denied)
    with pytest.raises(PermissionError) as info:
        io.write_text_atomic(tmp_path / "ro.txt", "x")
    assert info.value.filename == str(tmp_path / "ro.txt")
    assert blocker.read_text() == "keep" and [p.name for p in tmp_path.iterdir()] == ["afile"]


class TestProcStatus:
    @pytest.mark.skipif(not Path("/proc/self/status").is_file(), reason="no /proc (not Linux)")
    def test_known_lines_and_a_missing_one(self):
        rss = int(io.proc_status("VmRSS"))  # kB now; the peak read after it holds it
        assert int(io.proc_status("VmHWM")) >= rss > 0
        assert int(io.proc_status("Umask"), 8) == io.current_umask()
        assert io.proc_status("NoSuchLine") is None

    def test_without_proc(self, monkeypatch):
        def no_file(*a, **k):
            raise FileNotFoundError("/proc/self/status")

        monkeypatch.setattr("builtins.open", no_file)
        assert io.proc_status("VmHWM") is None


def test_write_jsonl_atomic_writes_one_line_per_row(tmp_path: Path):
    import json

    rows = [{"frame": 0, "events": []}, {"frame": 1, "events": ["lost"]}]
    out = io.write_jsonl_atomic(tmp_path / "f.jsonl", rows)
    assert out == tmp_path / "f.jsonl"
    assert [json.loads(ln) for ln in out.read_text().splitlines()] == rows
    assert io.write_jsonl_atomic(tmp_path / "empty.jsonl", []).read_text() == ""
