"""Settings that make a dynamic-mode run of a few tiny synthetic frames take seconds (shared by
the tests that run one end to end), the tiny walker scene they run on, and starting the motion
check early for such short clips (``early_check``: an autouse fixture for the modules that import
it; ``walker_fixture``: a module-scoped fixture rendering the walker once)."""

import numpy as np
import pytest


def tiny_sets(first_iters: int = 20, ba_rays: int = 256, threads: int = 1) -> list[str]:
    """``--set`` arguments: a small map, few iterations and rays, the weightless encoder."""
    sets = ["map.n_levels=4", "map.log2_hashmap_size=12", "map.voxel_size=0.1",
            f"mapping.first_iters={first_iters}", "tracking.iters=3", "tracking.n_rays=128", "mapping.iters=3",
            f"mapping.n_rays={ba_rays}", "tracking.ignore_border=2", f"run.threads={threads}",
            "run.mesh_resolution=0.1", "mapping.every=2", "mapping.keyframe_every=2",
            "motion.encoder=color-hist", "motion.check_width=48"]
    return [a for s in sets for a in ("--set", s)]


def check_from_frame_2(monkeypatch) -> None:
    """The inconsistency check from frame 2 on (its warm-up is 5 frames): these clips are short."""
    monkeypatch.setattr("dynslam_cli.run.loop.CHECK_WARMUP", 2)


@pytest.fixture(autouse=True)
def early_check(monkeypatch):
    """The check from frame 2 on, for every test of a module that imports this fixture."""
    check_from_frame_2(monkeypatch)


def walker_fixture(width: int, height: int, frames: int):
    """A module-scoped fixture: the tiny walker scene at this size, rendered once per module."""

    @pytest.fixture(scope="module")
    def walker(tmp_path_factory):
        return render_walker(tmp_path_factory, width, height, frames)

    return walker


def render_walker(tmp_path_factory, width: int, height: int, frames: int):
    """A tiny synthetic walker scene (scene seed 3) in a fresh temporary folder."""
    from dynslam_cli.synth.config import SynthConfig
    from dynslam_cli.synth.render import render_preset

    out = tmp_path_factory.mktemp("synth") / "walker"
    render_preset("walker", out, SynthConfig(width=width, height=height, frames=frames, seed=3), progress=False)
    return out


def read_traj(path) -> np.ndarray:
    """A TUM trajectory file as an N×8 array (timestamp, t, q)."""
    rows = [ln.split() for ln in path.read_text().splitlines() if ln and not ln.startswith("#")]
    return np.array([[float(v) for v in r] for r in rows])
