"""A non-editable install works: the wheel ships configs/ (setup.py's build step) and
``configs_dir()`` finds them outside a checkout.

The wheel is built offline from a copy of the source tree (``pip wheel --no-deps
--no-build-isolation --no-index``), installed with pip into a target folder (the dependencies
come from this venv) and run from a folder outside the checkout.
"""

import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SOURCES = ("pyproject.toml", "setup.py", "MANIFEST.in", "README.md", "LICENSE", "configs", "dynslam_cli")
CONFIGS = sorted(str(p.relative_to(REPO / "configs")) for p in (REPO / "configs").glob("**/*.yaml"))


def _pip(*args, cwd=None):
    r = subprocess.run([sys.executable, "-m", "pip", *args], capture_output=True, text=True, timeout=600, cwd=cwd)
    assert r.returncode == 0, f"pip {' '.join(args)} failed:\n{r.stdout}\n{r.stderr}"


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("pkg")
    src = root / "src"
    src.mkdir()
    for name in SOURCES:
        p = REPO / name
        if p.is_dir():
            shutil.copytree(p, src / name, ignore=shutil.ignore_patterns("__pycache__", "_configs", "*.egg-info"))
        else:
            shutil.copy2(p, src / name)
    _pip("wheel", "-q", "--no-deps", "--no-build-isolation", "--no-index", str(src), "-w", str(root / "wheels"))
    wheels = list((root / "wheels").glob("dynslam_cli-*.whl"))
    assert len(wheels) == 1
    return wheels[0]


@pytest.fixture(scope="module")
def installed(wheel, tmp_path_factory) -> Path:
    site = tmp_path_factory.mktemp("site")
    _pip("install", "-q", "--no-deps", "--no-index", "--target", str(site), str(wheel))
    return site


def test_the_wheel_ships_the_configs(wheel):
    assert "base.yaml" in CONFIGS and "bonn.yaml" in CONFIGS and "presets/coslam.yaml" in CONFIGS
    with zipfile.ZipFile(wheel) as z:
        names = set(z.namelist())
        for name in CONFIGS:
            assert z.read(f"dynslam_cli/_configs/{name}") == (REPO / "configs" / name).read_bytes(), name
    assert not any(n.startswith("configs/") for n in names)
    assert "dynslam_cli/cli.py" in names and "dynslam_cli/view/recording.py" in names


def _env(site: Path) -> dict:
    env = dict(os.environ, PYTHONPATH=str(site))  # before this venv's editable install of the checkout
    env.pop("DYNSLAM_DATA", None)
    return env


def test_an_installed_copy_finds_its_configs_outside_the_checkout(installed, tmp_path):
    code = "import dynslam_cli, dynslam_cli.config as c; print(dynslam_cli.__file__); print(c.configs_dir())"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, env=_env(installed))
    assert r.returncode == 0, r.stderr
    pkg_file, cdir = r.stdout.split()
    assert Path(pkg_file).is_relative_to(installed), "imported the checkout, not the installed copy"
    assert Path(cdir) == installed / "dynslam_cli" / "_configs"


def test_installed_console_script_shows_the_bonn_config(installed, tmp_path):
    script = installed / "bin" / "dynslam"
    assert script.is_file()
    r = subprocess.run([sys.executable, str(script), "config", "show", "--seq", "bonn/crowd"], capture_output=True,
                       text=True, cwd=tmp_path, env=_env(installed))
    assert r.returncode == 0, r.stderr
    # the same resolved config as the checkout's (configs/bonn.yaml: max_depth 3.178, the Bonn intrinsics)
    ref = subprocess.run([sys.executable, "-m", "dynslam_cli.cli", "config", "show", "--seq", "bonn/crowd"],
                         capture_output=True, text=True, cwd=REPO)
    assert ref.returncode == 0, ref.stderr
    assert r.stdout == ref.stdout and "max_depth: 3.178" in r.stdout
