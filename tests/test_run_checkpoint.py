"""dynslam_cli.run.checkpoint: what a checkpoint belongs to, and the first difference named."""

import pytest

from dynslam_cli.errors import DynslamError
from dynslam_cli.run import checkpoint


def _identity(**over):
    seq = {"spec": "synth/walker", "dataset": "synth", "name": "walker", "frames": 5, "frames_sha256": "a" * 64}
    ident = {"sequence": seq, "config": {"tracking.iters": 10, "run.checkpoint_every": 50}, "code": "0.1.0"}
    for k, v in over.items():
        ident[k] = v
    return ident


class TestFlatten:
    def test_nested(self):
        assert checkpoint.flatten({"a": {"b": 1, "c": {"d": [2]}}, "e": None}) == {"a.b": 1, "a.c.d": [2], "e": None}


class TestIdentityMismatch:
    def test_same(self):
        assert checkpoint.identity_mismatch(_identity(), _identity()) is None

    def test_free_keys_may_differ(self):
        new = _identity(config={"tracking.iters": 10, "run.checkpoint_every": 5})
        assert checkpoint.identity_mismatch(_identity(), new) is None

    def test_config_key_named_with_both_values(self):
        new = _identity(config={"tracking.iters": 12, "run.checkpoint_every": 50})
        assert checkpoint.identity_mismatch(_identity(), new) == "config key tracking.iters differs (old 10, new 12)"

    def test_sequence_and_code(self):
        other = dict(_identity()["sequence"], name="crowd")
        assert "old synth/walker, new synth/crowd" in checkpoint.identity_mismatch(_identity(), _identity(sequence=other))
        assert checkpoint.identity_mismatch(_identity(), _identity(code="0.2.0")) == \
            "code version differs (old 0.1.0, new 0.2.0)"

    def test_device_kind(self):
        # a checkpoint written before the device was recorded ran on the CPU
        assert checkpoint.identity_mismatch(_identity(), _identity(device="cpu")) is None
        msg = checkpoint.identity_mismatch(_identity(device="cuda"), _identity(device="cpu"))
        assert msg == "device differs (the checkpoint ran on cuda, this run would use cpu: pass --device cuda)"


class TestResumeState:
    def test_unreadable_file(self, tmp_path):
        p = tmp_path / "checkpoint.pt"
        p.write_bytes(b"not a checkpoint")
        with pytest.raises(DynslamError, match="cannot read checkpoint"):
            checkpoint.resume_state(p, _identity())
