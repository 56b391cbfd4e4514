"""3-D viewing of run folders: a Rerun recording (``dynslam view``; the optional ``view`` extra)."""
