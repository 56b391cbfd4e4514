"""Numba's thread pool: which threading layer the parallel kernels use.

Numba picks OpenMP by default where it can.  OpenMP worker threads spin-wait between parallel
regions, and dynslam launches thousands of short regions (a hash-grid pass per iteration) between
torch operations: when another process keeps a core busy (a second benchmark, a browser, CI's
neighbour), the spinning workers and the main thread fight over the remaining core.  Measured on
the 2-core dev machine with one core busy elsewhere and one thread, a tracking step took 359 ms
with the OpenMP layer and 35 ms with numba's own ``workqueue`` layer (benchmarks/bench_threading.py).
So dynslam selects ``workqueue`` unless the user chose a layer with ``NUMBA_THREADING_LAYER``.
``workqueue`` must not launch parallel kernels from several Python threads at once (numba aborts
then): a library user who runs dynslam in concurrent threads sets ``NUMBA_THREADING_LAYER=omp``
(dynslam's own parallelism uses processes).
"""

from __future__ import annotations

import os

DEFAULT_LAYER = "workqueue"


def configure_numba_layer() -> str:
    """Select the threading layer before numba launches its first parallel region; returns the
    configured layer name (the user's ``NUMBA_THREADING_LAYER`` when set)."""
    import numba

    user = os.environ.get("NUMBA_THREADING_LAYER")
    if user:
        return user
    numba.config.THREADING_LAYER = DEFAULT_LAYER
    return DEFAULT_LAYER
