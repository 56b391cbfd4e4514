"""dynslam_cli.utils.threads: seeding, deterministic torch, thread counts."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import torch

from dynslam_cli.utils.threads import deterministic_torch, seed_everything, set_threads


class TestDeterministicTorch:
    def test_sets_deterministic_warn_only(self):
        before = (torch.are_deterministic_algorithms_enabled(), torch.is_deterministic_algorithms_warn_only_enabled())
        try:
            torch.use_deterministic_algorithms(False)
            deterministic_torch()
            assert torch.are_deterministic_algorithms_enabled()
            assert torch.is_deterministic_algorithms_warn_only_enabled()
        finally:
            torch.use_deterministic_algorithms(before[0], warn_only=before[1])

    def test_does_not_import_dynamo(self):
        # torch.use_deterministic_algorithms imports torch._inductor, and with it torch._dynamo (2 s)
        code = ("import sys\nfrom dynslam_cli.utils.threads import seed_everything\nseed_everything(0)\n"
                "import torch\nprint(torch.are_deterministic_algorithms_enabled(), 'torch._dynamo' in sys.modules)\n")
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
        assert out.stdout.split() == ["True", "False"]


class TestSeedEverything:
    def test_repeatable(self):
        draws = []
        for _ in range(2):
            seed_everything(3)
            draws.append((np.random.rand(), float(torch.rand(1))))
        assert draws[0] == draws[1]


class TestSetThreads:
    def test_count(self):
        before = torch.get_num_threads()
        try:
            assert set_threads(1) == 1 and torch.get_num_threads() == 1
        finally:
            set_threads(before)  # torch's and numba's


class TestPassiveOpenmp:
    @staticmethod
    def _policy(env_policy):
        import os

        env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
        if env_policy is not None:
            env["OMP_WAIT_POLICY"] = env_policy
        # importing the package sets the policy before anything imports torch (libgomp reads it when it loads)
        code = "import os, dynslam_cli, torch\nprint(os.environ['OMP_WAIT_POLICY'])\n"
        return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                              env=env).stdout.strip()

    def test_passive_unless_the_user_set_one(self):
        assert self._policy(None) == "PASSIVE"
        assert self._policy("ACTIVE") == "ACTIVE"

    def test_returns_the_policy_in_force(self, monkeypatch):
        from dynslam_cli.utils.threads import passive_openmp

        monkeypatch.delenv("OMP_WAIT_POLICY", raising=False)
        assert passive_openmp() == "PASSIVE"
        monkeypatch.setenv("OMP_WAIT_POLICY", "active")
        assert passive_openmp() == "active"
