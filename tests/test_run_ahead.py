"""ReadAhead: frames read (and worked on) one frame ahead in a background thread."""

from __future__ import annotations

import threading
import time
from contextlib import closing

import pytest

from dynslam_cli.run.ahead import ReadAhead


class _Seq:
    """Indexable frames that record which thread read them and in which order."""

    def __init__(self, n, fail_at=None):
        self.n, self.fail_at, self.reads, self.threads = n, fail_at, [], set()

    def __len__(self):
        return self.n

    def __getitem__(self, i):
        if i == self.fail_at:
            raise OSError(f"frame {i} unreadable")
        self.reads.append(i)
        self.threads.add(threading.current_thread().name)
        return {"index": i}


class TestReadAhead:
    def test_items_in_order_with_their_work(self):
        seq = _Seq(5)
        out = list(ReadAhead(seq, 1, 5, lambda f: f["index"] * 10))
        assert [(i, f["index"], r) for i, f, r in out] == [(1, 1, 10), (2, 2, 20), (3, 3, 30), (4, 4, 40)]
        assert seq.reads == [1, 2, 3, 4]  # each frame read once
        assert all(name.startswith("dynslam-ahead") for name in seq.threads)

    def test_without_work_and_empty_range(self):
        assert [(i, r) for i, _, r in ReadAhead(_Seq(3), 0, 3)] == [(0, None), (1, None), (2, None)]
        assert list(ReadAhead(_Seq(3), 3, 3)) == []

    def test_next_frame_worked_on_while_the_body_runs(self):
        started = threading.Event()

        def work(frame):
            if frame["index"] == 1:
                started.set()
            return frame["index"]

        for i, _, _ in ReadAhead(_Seq(2), 0, 2, work):
            if i == 0:  # frame 1 is read and worked on without the loop asking for it
                assert started.wait(5.0)

    def test_worker_error_raised_at_its_frame(self):
        got = []
        with pytest.raises(OSError, match="frame 2 unreadable"):
            for i, _, _ in ReadAhead(_Seq(4, fail_at=2), 0, 4):
                got.append(i)
        assert got == [0, 1]

    def test_closing_early_waits_for_the_worker_and_reads_no_further(self):
        seq = _Seq(10)

        def slow(frame):
            time.sleep(0.05)
            return frame["index"]

        with closing(iter(ReadAhead(seq, 0, 10, slow))) as it:
            for i, _, _ in it:
                if i == 2:
                    break
        n_reads = len(seq.reads)
        assert n_reads in (3, 4)  # frames 0-2, and the one read ahead of frame 2 if it had started
        time.sleep(0.2)
        assert len(seq.reads) == n_reads
        assert not any(t.name.startswith("dynslam-ahead") for t in threading.enumerate())

    def test_the_worker_runs_torch_at_the_callers_thread_count(self):
        """Torch sets a new thread's count at its first parallel operation from the process's count at
        that moment, which the classifier lowers to 1 for a moment: the worker keeps its caller's."""
        import torch

        old = torch.get_num_threads()
        gate = threading.Event()

        def lower_then_open():
            torch.set_num_threads(1)  # as the classifier does, before the worker's first operation
            gate.set()

        try:
            torch.set_num_threads(2)
            threading.Timer(0.05, lower_then_open).start()
            with closing(iter(ReadAhead(_Seq(2), 0, 2, lambda f: gate.wait(5) and torch.get_num_threads()))) as it:
                assert [r for _, _, r in it] == [2, 2]
        finally:
            torch.set_num_threads(old)
