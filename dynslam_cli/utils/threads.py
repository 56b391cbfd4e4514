"""Numba's thread pool: which threading layer the parallel kernels use.

Numba picks OpenMP where it can, and on an idle machine that is the fastest layer.  OpenMP worker
threads spin-wait between parallel regions, though, and dynslam launches thousands of short regions
(a hash-grid pass per iteration) between torch operations: beside other work the spinning costs
dearly.  Measured with benchmarks/bench_threading.py on the 2-core dev machine, one thread, ms per
tracking step (OpenMP / numba's own ``workqueue`` layer): idle 21 / 32, beside a busy loop 58 / 28,
beside a second dynslam run 359 / 29.

So a run with one thread (``run.threads=1``, what the README advises on a shared machine and what
the benchmarks and ablation workers use side by side) selects ``workqueue``; runs with more threads
keep numba's choice.  ``NUMBA_THREADING_LAYER`` set by the user always wins.  ``workqueue`` must not
launch kernels from several Python threads at once (numba aborts then); dynslam's own parallelism
uses processes.
"""

from __future__ import annotations

import os
from typing import Optional

SHARED_LAYER = "workqueue"


def choose_numba_layer(threads: int) -> Optional[str]:
    """Call before numba's first parallel launch in the process: ``workqueue`` for a one-thread run
    unless ``NUMBA_THREADING_LAYER`` is set.  Returns the layer asked for (None = numba's choice).
    After the first launch numba keeps the layer it started with, whatever is asked."""
    user = os.environ.get("NUMBA_THREADING_LAYER")
    if user:
        return user
    if int(threads) != 1:
        return None
    try:
        import numba
    except ImportError:
        return None
    numba.config.THREADING_LAYER = SHARED_LAYER
    return SHARED_LAYER
