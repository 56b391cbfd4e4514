"""Settings that make a dynamic-mode run of a few tiny synthetic frames take seconds (shared by
the tests that run one end to end), and starting the motion check early for such short clips."""


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
    monkeypatch.setattr("dynslam_cli.run.dynamic.CHECK_WARMUP", 2)
