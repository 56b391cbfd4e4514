"""Frames read, and optionally worked on, one frame ahead in a background thread.

While the caller tracks, checks and maps frame i, one worker thread reads frame i+1 from the sequence
and runs ``work`` on it: in dynamic mode the motion module's :meth:`~dynslam_cli.motion.module.
MotionModule.perceive` (segmenting and encoding, which depend on the frame's pixels alone).  The two
streams share the cores: torch, onnxruntime, OpenCV and numba's compiled kernels release the GIL.

The results are those of doing the same work in order: ``work`` sees only the frame, each item is
computed once, and the items come out in frame order.  An exception in the worker is raised by the
iteration that reaches its frame; closing the iterator (the loop left early, an error, Ctrl-C) waits
for the running item and drops the rest.  ``waited_ms`` is how long the caller waited for the last
item: the part of the read and the work the caller's own frame did not hide.
"""

from __future__ import annotations

import time
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, Callable, Iterator, Optional, Sequence

from dynslam_cli.utils.threads import same_torch_threads


class ReadAhead:
    """``for i, frame, result in ReadAhead(seq, start, stop, work): ...`` over frames ``start`` to
    ``stop - 1`` of ``seq`` (anything indexable), ``result = work(frame)`` (None without ``work``);
    frame i+1 is read and worked on while the body runs for frame i."""

    def __init__(self, seq: Sequence, start: int, stop: int, work: Optional[Callable[[Any], Any]] = None):
        self.seq, self.start, self.stop, self.work = seq, int(start), int(stop), work
        self.waited_ms = 0.0

    def _load(self, i: int) -> tuple[Any, Any]:
        frame = self.seq[i]
        return frame, (None if self.work is None else self.work(frame))

    def __iter__(self) -> Iterator[tuple[int, Any, Any]]:
        if self.start >= self.stop:
            return
        import torch

        pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="dynslam-ahead",
                                  initializer=same_torch_threads, initargs=(torch.get_num_threads(),))
        try:
            pending: Future = pool.submit(self._load, self.start)
            for i in range(self.start, self.stop):
                t0 = time.perf_counter()
                frame, result = pending.result()
                self.waited_ms = (time.perf_counter() - t0) * 1e3
                if i + 1 < self.stop:
                    pending = pool.submit(self._load, i + 1)
                yield i, frame, result
        finally:
            pool.shutdown(wait=True, cancel_futures=True)
