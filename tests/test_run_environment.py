"""run/environment.py: what a run records about the machine and libraries it ran on."""

import os
import time

import numpy as np
import torch

from dynslam_cli.run.environment import LIBRARIES, cpu_model, cpu_seconds, peak_rss_mb, versions


class TestVersions:
    def test_the_libraries_a_trajectory_depends_on(self):
        v = versions(torch.device("cpu"))
        assert v["python"] and v["torch"] == torch.__version__ and v["numpy"] == np.__version__
        assert v["cpu"] == cpu_model() and "gpu" not in v and "cuda" not in v
        assert set(LIBRARIES) <= set(v)  # every dependency of the package is installed here
        assert v["numba_threading_layer"]
        assert v["omp_wait_policy"] == os.environ.get("OMP_WAIT_POLICY", "")


class TestCpuSeconds:
    def test_counts_every_threads_work(self):
        from concurrent.futures import ThreadPoolExecutor

        def work(cpu_s=0.15):  # until this thread alone has used cpu_s of CPU time
            t = time.thread_time()
            while time.thread_time() - t < cpu_s:
                pass

        c0, w0 = cpu_seconds(), time.perf_counter()
        with ThreadPoolExecutor(2) as pool:
            list(pool.map(work, [0.15, 0.15]))
        used, wall = cpu_seconds() - c0, time.perf_counter() - w0
        assert 0.3 <= used <= (os.cpu_count() or 1) * wall + 0.05  # both threads' time, seconds not ms or ticks


class TestPeakRss:
    def test_at_least_what_the_process_holds_now_in_mib(self):
        from dynslam_cli.utils.io import proc_status

        block = np.ones(256 * 2 ** 20 // 8)  # 256 MiB, written
        rss = proc_status("VmRSS")  # "123456" (kB) on Linux
        now_mib = int(rss.split()[0]) / 1024.0 if rss else 256.0
        assert block.sum() > 0 and now_mib >= 256
        assert peak_rss_mb() >= now_mib  # MiB, not kB or bytes
        assert peak_rss_mb() < 64 * 1024
