"""Build hook: ship the repository's ``configs/*.yaml`` and ``configs/presets/*.yaml`` inside the package.

``configs/`` at the repository root stays the source of truth; a built wheel (``pip install .``,
``pip wheel .``) carries a copy as ``dynslam_cli/_configs/``, which
:func:`dynslam_cli.config.loader.configs_dir` falls back to when the package does not run from a
checkout.  All metadata lives in pyproject.toml.
"""

from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

CONFIGS = Path(__file__).resolve().parent / "configs"
PACKAGE_DIR = "_configs"


class BuildPyWithConfigs(build_py):
    """``build_py`` that also copies ``configs/*.yaml`` and ``configs/presets/*.yaml`` into
    ``<build_lib>/dynslam_cli/_configs`` (the presets into its ``presets/``)."""

    def _config_files(self):
        files = sorted(CONFIGS.glob("*.yaml")) + sorted(CONFIGS.glob("presets/*.yaml"))
        if not (CONFIGS / "base.yaml").is_file():
            raise SystemExit(f"cannot build dynslam_cli: {CONFIGS / 'base.yaml'} not found")
        return files

    def _targets(self):
        dst = Path(self.build_lib) / "dynslam_cli" / PACKAGE_DIR
        return [(src, dst / src.relative_to(CONFIGS)) for src in self._config_files()]

    def run(self):
        super().run()
        if getattr(self, "editable_mode", False):  # an editable install reads the checkout's configs/
            return
        for src, dst in self._targets():
            self.mkpath(str(dst.parent))
            self.copy_file(str(src), str(dst))

    def get_outputs(self, include_bytecode=True):
        outputs = super().get_outputs(include_bytecode)
        if getattr(self, "editable_mode", False):
            return outputs
        return outputs + [str(dst) for _, dst in self._targets()]


setup(cmdclass={"build_py": BuildPyWithConfigs})
