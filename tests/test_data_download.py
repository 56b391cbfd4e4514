"""`dynslam download` against a local threaded HTTP server (127.0.0.1, ephemeral port)."""

from __future__ import annotations

import io
import re
import tarfile
import threading
import zipfile
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import ClassVar

import pytest
from test_data_helpers import make_folder
from typer.testing import CliRunner

from dynslam_cli.cli import app
from dynslam_cli.data.download import (
    BONN_BASE,
    TUM_BASE,
    download,
    download_item,
    with_base,
)
from dynslam_cli.errors import DynslamError

TUM_PATH = "/rgbd/dataset/freiburg3/rgbd_dataset_freiburg3_walking_xyz.tgz"
BONN_PATH = "/html/projects/rgbd_dynamic2019/rgbd_bonn_crowd.zip"
REF_PATH = "/html/projects/rgbd_dynamic2019/rgbd_bonn_groundtruth_1mm_section.zip"


class Handler(BaseHTTPRequestHandler):
    files: ClassVar[dict] = {}
    short: ClassVar[set] = set()  # paths answered with a Content-Length larger than the body
    log: ClassVar[list] = []

    def do_GET(self):
        rng = self.headers.get("Range")
        self.log.append((self.path, rng))
        data = self.files.get(self.path)
        if data is None:
            self.send_error(404, "Not Found")
            return
        start = 0
        m = re.fullmatch(r"bytes=(\d+)-", rng or "")
        if m:
            start = int(m.group(1))
            if start >= len(data):
                self.send_response(416)
                self.send_header("Content-Range", f"bytes */{len(data)}")
                self.send_header("Content-Length", "0")
                self.end_headers()
                return
            self.send_response(206)
            self.send_header("Content-Range", f"bytes {start}-{len(data) - 1}/{len(data)}")
        else:
            self.send_response(200)
        body = data[start:]
        if self.path in self.short:
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Connection", "close")
            self.end_headers()
            self.wfile.write(body[: len(body) // 2])  # the connection drops half-way
            self.wfile.flush()
            self.close_connection = True
            return
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *args):
        pass


@pytest.fixture()
def server():
    Handler.files, Handler.short, Handler.log = {}, set(), []
    srv = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    srv.daemon_threads = True
    thread = threading.Thread(target=srv.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{srv.server_address[1]}", Handler
    finally:
        srv.shutdown()
        srv.server_close()
        thread.join(timeout=5)


def tgz_of(folder: Path, arcname: str) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as tf:
        tf.add(folder, arcname=arcname)
    return buf.getvalue()


def zip_of(folder: Path, arcname: str) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for p in sorted(folder.rglob("*")):
            zf.write(p, f"{arcname}/{p.relative_to(folder)}")
    return buf.getvalue()


@pytest.fixture()
def tum_archive(tmp_path: Path) -> bytes:
    src = make_folder(tmp_path / "src" / "tum", n=3)
    return tgz_of(src, "rgbd_dataset_freiburg3_walking_xyz")


def test_official_urls():
    assert download_item("tum/fr3_walking_xyz").url == f"{TUM_BASE}/freiburg3/rgbd_dataset_freiburg3_walking_xyz.tgz"
    assert TUM_BASE == "https://cvg.cit.tum.de/rgbd/dataset"
    assert download_item("tum/fr1_desk").url == "https://cvg.cit.tum.de/rgbd/dataset/freiburg1/rgbd_dataset_freiburg1_desk.tgz"
    assert download_item("bonn/crowd").url == "https://www.ipb.uni-bonn.de/html/projects/rgbd_dynamic2019/rgbd_bonn_crowd.zip"
    ref = download_item("bonn/reference")
    assert ref.url == f"{BONN_BASE}/rgbd_bonn_groundtruth_1mm_section.zip" and ref.folder == "rgbd_bonn_reference"
    assert with_base(ref.url, "http://m.example/x/") == "http://m.example/x" + REF_PATH
    for bad in ("tum/nope", "bonn/nope", "kitti/00", "tum"):
        with pytest.raises(DynslamError):
            download_item(bad)
    with pytest.raises(DynslamError, match="known bonn sequences: .*crowd.*reference"):
        download_item("bonn/crowdd")
    with pytest.raises(DynslamError, match="scheme"):
        with_base("https://a/b", "mirror.example")


def test_download_tgz_and_zip(server, tmp_path: Path, tum_archive: bytes):
    base, handler = server
    handler.files[TUM_PATH] = tum_archive
    handler.files[BONN_PATH] = zip_of(make_folder(tmp_path / "src" / "bonn", n=2), "rgbd_bonn_crowd")
    root = tmp_path / "data"
    results = download(["tum/fr3_walking_xyz", "bonn/crowd"], root, base_url=base, progress=False)
    assert [r.status for r in results] == ["downloaded", "downloaded"]
    assert results[0].bytes == len(tum_archive)
    assert sorted(p.name for p in root.iterdir()) == ["rgbd_bonn_crowd", "rgbd_dataset_freiburg3_walking_xyz"]
    assert (root / "rgbd_dataset_freiburg3_walking_xyz" / "rgb.txt").is_file()
    # the extracted folder honours the umask (mkdtemp alone gives 0700)
    from dynslam_cli.utils.io import default_mode

    assert (root / "rgbd_bonn_crowd").stat().st_mode & 0o777 == default_mode(folder=True)
    # the downloaded sequences open by name
    from dynslam_cli.config import load_config
    from dynslam_cli.data.open import open_sequence

    seq = open_sequence("bonn/crowd", load_config("bonn", "crowd", overrides=[f"data.root={root}"]))
    assert len(seq) == 2 and seq[1].depth.shape == (24, 32)
    # a second call finds them present and asks the server nothing
    n = len(handler.log)
    assert [r.status for r in download(["tum/fr3_walking_xyz"], root, base_url=base, progress=False)] == ["present"]
    assert len(handler.log) == n


def test_reference_zip_with_loose_files(server, tmp_path: Path):
    base, handler = server
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr("rgbd_bonn_groundtruth_1mm_section.ply", b"ply\nformat ascii 1.0\nend_header\n")
        zf.writestr("README.txt", b"reference cloud")
    handler.files[REF_PATH] = buf.getvalue()
    root = tmp_path / "data"
    download(["bonn/reference"], root, base_url=base, progress=False)
    from dynslam_cli.data.bonn import reference_cloud

    assert reference_cloud(root) == root / "rgbd_bonn_reference" / "rgbd_bonn_groundtruth_1mm_section.ply"
    assert sorted(p.name for p in root.iterdir()) == ["rgbd_bonn_reference"]


def test_resume_partial_download(server, tmp_path: Path, tum_archive: bytes):
    base, handler = server
    handler.files[TUM_PATH] = tum_archive
    root = tmp_path / "data"
    root.mkdir()
    half = len(tum_archive) // 2
    (root / "rgbd_dataset_freiburg3_walking_xyz.tgz.part").write_bytes(tum_archive[:half])
    download(["tum/fr3_walking_xyz"], root, base_url=base, progress=False)
    assert handler.log == [(TUM_PATH, f"bytes={half}-")]
    assert (root / "rgbd_dataset_freiburg3_walking_xyz" / "depth.txt").is_file()
    assert sorted(p.name for p in root.iterdir()) == ["rgbd_dataset_freiburg3_walking_xyz"]


def test_size_mismatch_then_resume(server, tmp_path: Path, tum_archive: bytes):
    base, handler = server
    handler.files[TUM_PATH] = tum_archive
    handler.short.add(TUM_PATH)
    root = tmp_path / "data"
    with pytest.raises(DynslamError) as info:
        download(["tum/fr3_walking_xyz"], root, base_url=base, progress=False)
    msg = str(info.value)
    assert "incomplete" in msg and f"of {len(tum_archive)} bytes" in msg and ".tgz.part" in msg
    part = root / "rgbd_dataset_freiburg3_walking_xyz.tgz.part"
    assert part.stat().st_size == len(tum_archive) // 2
    assert not (root / "rgbd_dataset_freiburg3_walking_xyz").exists()
    handler.short.clear()  # the server behaves again: the next run resumes
    download(["tum/fr3_walking_xyz"], root, base_url=base, progress=False)
    assert handler.log[-1] == (TUM_PATH, f"bytes={len(tum_archive) // 2}-")
    assert (root / "rgbd_dataset_freiburg3_walking_xyz" / "rgb.txt").is_file() and not part.exists()


def test_stale_partial_larger_than_file_restarts(server, tmp_path: Path, tum_archive: bytes):
    base, handler = server
    handler.files[TUM_PATH] = tum_archive
    root = tmp_path / "data"
    root.mkdir()
    (root / "rgbd_dataset_freiburg3_walking_xyz.tgz.part").write_bytes(b"x" * (len(tum_archive) + 10))
    download(["tum/fr3_walking_xyz"], root, base_url=base, progress=False)
    assert [r for _, r in handler.log] == [f"bytes={len(tum_archive) + 10}-", None]
    assert (root / "rgbd_dataset_freiburg3_walking_xyz" / "rgb.txt").is_file()


def test_http_error_and_corrupt_archive(server, tmp_path: Path):
    base, handler = server
    root = tmp_path / "data"
    with pytest.raises(DynslamError, match=r"rgbd_bonn_crowd\.zip failed: HTTP 404"):
        download(["bonn/crowd"], root, base_url=base, progress=False)
    handler.files[BONN_PATH] = b"this is not a zip archive"
    with pytest.raises(DynslamError, match=r"cannot extract .*rgbd_bonn_crowd\.zip"):
        download(["bonn/crowd"], root, base_url=base, progress=False)
    assert list(root.iterdir()) == []  # no folder, no temp folder, the broken archive removed


def test_cli_download_with_env_base(server, tmp_path: Path, tum_archive: bytes, monkeypatch):
    base, handler = server
    handler.files[TUM_PATH] = tum_archive
    monkeypatch.setenv("DYNSLAM_DOWNLOAD_BASE", base)
    runner = CliRunner()
    res = runner.invoke(app, ["download", "tum/fr3_walking_xyz", "--data-root", str(tmp_path / "d"), "--quiet"])
    assert res.exit_code == 0, res.output
    assert "extracted to" in res.output and (tmp_path / "d" / "rgbd_dataset_freiburg3_walking_xyz").is_dir()
    res = runner.invoke(app, ["download", "bonn/nope", "--data-root", str(tmp_path / "d")])
    assert res.exit_code == 2 and "error: unknown sequence 'bonn/nope'" in res.output and "Traceback" not in res.output
    res = runner.invoke(app, ["download", "bonn/crowd", "--data-root", str(tmp_path / "d"), "--base-url", base])
    assert res.exit_code == 2 and "HTTP 404" in res.output
