"""`dynslam download`: fetch official TUM / Bonn archives into the data root.

* TUM: ``https://cvg.cit.tum.de/rgbd/dataset/freiburgN/rgbd_dataset_freiburgN_<name>.tgz``
* Bonn: ``https://www.ipb.uni-bonn.de/html/projects/rgbd_dynamic2019/rgbd_bonn_<name>.zip``
* ``bonn/reference``: Bonn's laser-scanned reference cloud,
  ``…/rgbd_dynamic2019/rgbd_bonn_groundtruth_1mm_section.zip`` → ``<root>/rgbd_bonn_reference/``.

The archive is downloaded to ``<root>/<archive>.part`` (resumed with an HTTP Range request when
that file exists), checked against the Content-Length, renamed to ``<root>/<archive>``, extracted
into a temporary folder in the root and renamed into place (the archive's single top-level
folder, or the whole extraction when it has several entries); the archive is then removed.
A base URL (``--base-url`` or ``$DYNSLAM_DOWNLOAD_BASE``) replaces the scheme and server of the
official URL, keeping its path: ``http://mirror/prefix`` + ``/rgbd/dataset/freiburg3/….tgz``.
"""

from __future__ import annotations

import http.client
import os
import re
import shutil
import sys
import tarfile
import tempfile
import zipfile
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import urlsplit

from dynslam_cli.data.names import folder_name, identify, known_names
from dynslam_cli.errors import DynslamError
from dynslam_cli.utils.io import default_mode

TUM_BASE = "https://cvg.cit.tum.de/rgbd/dataset"
BONN_BASE = "https://www.ipb.uni-bonn.de/html/projects/rgbd_dynamic2019"
CHUNK = 1 << 20


@dataclass(frozen=True)
class DownloadItem:
    key: str  # tum/fr3_walking_xyz, bonn/crowd, bonn/reference
    url: str
    archive: str  # file name of the archive
    folder: str  # folder created under the data root


@dataclass
class DownloadResult:
    key: str
    folder: Path
    status: str  # "downloaded" or "present"
    bytes: int = 0


def download_item(name: str) -> DownloadItem:
    """The archive of a sequence name (``tum/…``, ``bonn/…`` or ``bonn/reference``)."""
    from dynslam_cli.data.bonn import REFERENCE_ARCHIVE, REFERENCE_FOLDER

    text = name.strip().strip("/")
    dataset, _, short = text.partition("/")
    if dataset == "bonn" and short == "reference":
        return DownloadItem(text, f"{BONN_BASE}/{REFERENCE_ARCHIVE}", REFERENCE_ARCHIVE, REFERENCE_FOLDER)
    if dataset not in ("tum", "bonn") or not short or "/" in short:
        raise DynslamError(f"cannot download '{name}': give tum/NAME, bonn/NAME or bonn/reference "
                           f"(e.g. tum/fr3_walking_xyz, bonn/crowd)")
    folder = folder_name(dataset, short)
    if folder is None:
        extra = ", reference" if dataset == "bonn" else ""
        raise DynslamError(f"unknown sequence '{text}'; known {dataset} sequences: "
                           f"{', '.join(known_names(dataset))}{extra}")
    key = identify(text).key
    if dataset == "tum":
        n = re.match(r"rgbd_dataset_freiburg(\d)_", folder).group(1)
        return DownloadItem(key, f"{TUM_BASE}/freiburg{n}/{folder}.tgz", f"{folder}.tgz", folder)
    return DownloadItem(key, f"{BONN_BASE}/{folder}.zip", f"{folder}.zip", folder)


def with_base(url: str, base: str | None) -> str:
    """Replace the scheme and server of ``url`` by ``base`` (which may carry a path prefix)."""
    if not base:
        return url
    if not re.match(r"^[a-zA-Z][a-zA-Z0-9+.-]*://", base):
        raise DynslamError(f"base URL '{base}' must start with a scheme such as http:// or https://")
    return base.rstrip("/") + urlsplit(url).path


def _open(url: str, offset: int, timeout: float):
    from urllib.error import HTTPError, URLError
    from urllib.request import Request, urlopen

    headers = {"User-Agent": "dynslam-download"}
    if offset:
        headers["Range"] = f"bytes={offset}-"
    try:
        return urlopen(Request(url, headers=headers), timeout=timeout)
    except HTTPError as exc:
        if exc.code == 416 and offset:
            return None  # the partial file is not a prefix the server can continue
        raise DynslamError(f"download of {url} failed: HTTP {exc.code} {exc.reason}") from None
    except (URLError, OSError) as exc:
        reason = getattr(exc, "reason", exc)
        raise DynslamError(f"cannot reach {url}: {reason}") from None


def fetch(url: str, dest: Path, progress: bool = True, timeout: float = 60.0) -> int:
    """Download ``url`` to ``dest`` via ``dest.part`` (resumed when present); returns the size."""
    from tqdm import tqdm

    dest = Path(dest)
    part = dest.with_name(dest.name + ".part")
    have = part.stat().st_size if part.is_file() else 0
    resp = _open(url, have, timeout)
    if resp is None:  # 416: start over
        part.unlink()
        have = 0
        resp = _open(url, 0, timeout)
    with resp:
        length = resp.headers.get("Content-Length")
        length = int(length) if length and length.isdigit() else None
        if have and resp.status == 206:
            m = re.match(r"bytes (\d+)-(\d+)/(\d+|\*)", resp.headers.get("Content-Range", ""))
            if not m or int(m.group(1)) != have:
                raise DynslamError(f"download of {url}: the server answered the resume request from byte "
                                   f"{have} with Content-Range '{resp.headers.get('Content-Range')}'; "
                                   f"remove {part} and run again")
            mode = "ab"
        else:
            have, mode = 0, "wb"  # server ignored the Range header: whole file again
        expected = have + length if length is not None else None
        with open(part, mode) as f, tqdm(total=expected, initial=have, unit="B", unit_scale=True,
                                        unit_divisor=1024, desc=dest.name, disable=not progress,
                                        file=sys.stderr, leave=True) as bar:
            while True:
                try:
                    chunk = resp.read(CHUNK)
                except http.client.IncompleteRead as exc:
                    f.write(exc.partial)
                    bar.update(len(exc.partial))
                    break
                except OSError as exc:  # timeout, reset: keep the .part for resuming
                    raise DynslamError(f"download of {url} interrupted after {f.tell()} bytes ({exc}); "
                                       f"run the command again to resume from {part}") from None
                if not chunk:
                    break
                f.write(chunk)
                bar.update(len(chunk))
    size = part.stat().st_size
    if expected is not None and size != expected:
        if size < expected:
            raise DynslamError(f"download of {url} incomplete: {size} of {expected} bytes (Content-Length); "
                               f"run the command again to resume from {part}")
        part.unlink()
        raise DynslamError(f"download of {url}: size mismatch, got {size} bytes but Content-Length "
                           f"says {expected}; partial file removed")
    os.replace(part, dest)
    return size


def extract(archive: Path, root: Path, folder: str) -> Path:
    """Extract a .tgz/.tar.gz/.zip into ``root/folder`` atomically (temp folder, then rename)."""
    archive, root = Path(archive), Path(root)
    target = root / folder
    tmp = Path(tempfile.mkdtemp(prefix=f".{folder}.extract-", dir=root))
    os.chmod(tmp, default_mode(folder=True))  # mkdtemp makes it 0700; the dataset folder honours the umask
    try:
        try:
            if archive.name.endswith((".tgz", ".tar.gz", ".tar")):
                with tarfile.open(archive) as tf:
                    tf.extractall(tmp, filter="data")
            elif archive.name.endswith(".zip"):
                with zipfile.ZipFile(archive) as zf:
                    for info in zf.infolist():
                        p = Path(info.filename)
                        if p.is_absolute() or ".." in p.parts:
                            raise DynslamError(f"archive {archive} holds an unsafe path: {info.filename}")
                    zf.extractall(tmp)
            else:
                raise DynslamError(f"cannot extract {archive}: unknown archive type (expected .tgz or .zip)")
        except (tarfile.TarError, zipfile.BadZipFile, EOFError, OSError) as exc:
            raise DynslamError(f"cannot extract {archive}: {exc}") from None
        entries = [p for p in tmp.iterdir() if p.name != "__MACOSX"]
        if not entries:
            raise DynslamError(f"archive {archive} is empty")
        src = entries[0] if len(entries) == 1 and entries[0].is_dir() else tmp
        if target.exists():
            raise DynslamError(f"cannot extract {archive}: {target} already exists")
        os.replace(src, target)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return target


def download(names: Iterable[str], root: Path, base_url: str | None = None,
             progress: bool = True, timeout: float = 60.0) -> list[DownloadResult]:
    """Download and extract each named sequence into ``root``; already present folders are skipped."""
    items = [download_item(n) for n in names]  # all names checked before any download
    if not items:
        raise DynslamError("nothing to download: give one or more names, e.g. tum/fr3_walking_xyz bonn/crowd")
    base = base_url if base_url is not None else os.environ.get("DYNSLAM_DOWNLOAD_BASE") or None
    root = Path(root)
    try:
        root.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DynslamError(f"cannot create data root {root}: {exc.strerror or exc}") from None
    results = []
    for item in items:
        target = root / item.folder
        if target.is_dir():
            results.append(DownloadResult(item.key, target, "present"))
            continue
        archive = root / item.archive
        if archive.is_file():  # complete (renamed from .part after the size check), not yet extracted
            size = archive.stat().st_size
        else:
            size = fetch(with_base(item.url, base), archive, progress=progress, timeout=timeout)
        try:
            extract(archive, root, item.folder)
        except DynslamError as exc:
            if not (root / item.folder).exists():  # a broken archive: fetch it anew next time
                archive.unlink(missing_ok=True)
                raise DynslamError(f"{exc} (archive removed; run again to download it anew)") from None
            raise
        archive.unlink()
        results.append(DownloadResult(item.key, target, "downloaded", size))
    return results
