"""Running a sequence end to end: the run folder, checkpoints, resume."""
