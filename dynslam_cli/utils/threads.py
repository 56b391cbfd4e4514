"""Numba's thread pool: which threading layer the parallel kernels use; how torch's OpenMP threads wait.

Numba picks OpenMP where it can; at one thread on an idle machine it is the faster layer.  OpenMP worker
threads spin-wait between parallel regions, though, and dynslam launches thousands of short regions
(a hash-grid pass per iteration) between torch operations: beside other work the spinning costs
dearly.  Measured with benchmarks/bench_threading.py on the 2-core dev machine, one thread, ms per
tracking step (OpenMP / numba's own ``workqueue`` layer): idle 21 / 32, beside a busy loop 58 / 28,
beside a second dynslam run 359 / 29.

With 2 threads on the idle (but noisy) machine the whole pipeline showed no consistent winner:
synth/static 150 frames at 640x480 ran at 0.89 fps with OpenMP against 1.15 with ``workqueue``,
the Bonn clip in dynamic mode 0.59 against 0.88, ``make demo`` 0.73 against 0.66.  So every run
selects ``workqueue`` for its behaviour under load; ``NUMBA_THREADING_LAYER`` set by the user wins.
``workqueue`` must not launch kernels from several Python threads at once (numba aborts then);
dynslam's own parallelism uses processes.

Torch's own OpenMP threads (GNU libgomp: torch's and MKL's parallel regions) spin the same way after each region,
and a run alternates them with numba's kernels thousands of times a frame, while the read-ahead thread
(``run/ahead.py``) encodes beside the loop.  :func:`passive_openmp` (called when ``dynslam_cli`` is imported, before
torch is: libgomp reads the setting once, when it loads) makes them sleep instead unless the user set
``OMP_WAIT_POLICY``.  Bonn clip, 2 threads, idle, alternating (docs/experiments.md, "OpenMP threads that sleep"):
the same bits, static and dynamic mode both faster.  A program that imports torch before dynslam keeps libgomp's
default; set ``OMP_WAIT_POLICY=PASSIVE`` in its environment then.

Determinism: with the same seed, thread count and machine a run is bit-for-bit repeatable
(tests/test_determinism.py).  :func:`seed_everything` switches torch to its deterministic
algorithms: on CPU, autograd's backward of indexing with repeated indices (bundle adjustment
gathers with ``index_select`` for that reason, but other indexing remains) otherwise scatter-adds
with atomic float adds from several threads, in an order that changes from run to run.
:func:`set_threads` picks the numba layer before it starts numba's pool.
"""

from __future__ import annotations

import os
import random
from typing import Optional

SHARED_LAYER = "workqueue"


def passive_openmp() -> str:
    """``OMP_WAIT_POLICY=PASSIVE`` unless the environment sets it (it takes effect only before torch is
    first imported); returns the policy in force from then on."""
    return os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def choose_numba_layer() -> Optional[str]:
    """``workqueue`` unless ``NUMBA_THREADING_LAYER`` is set; the modules holding dynslam's parallel
    kernels call it on import, before numba's first parallel launch (after it, numba keeps the
    layer it started with).  Returns the layer asked for (None = numba missing)."""
    user = os.environ.get("NUMBA_THREADING_LAYER")
    if user:
        return user
    try:
        import numba
    except ImportError:
        return None
    numba.config.THREADING_LAYER = SHARED_LAYER
    return SHARED_LAYER


def deterministic_torch() -> None:
    """Torch's deterministic algorithms (warnings, not errors, for an op that has none), without
    filling new tensors with NaN (every kernel here writes all of its output); cuBLAS gets the
    workspace setting its deterministic mode needs unless the user set one."""
    import torch

    os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
    # torch.use_deterministic_algorithms also sets torch._inductor's flag, and importing torch._inductor imports
    # torch._dynamo (2 s on a 2-core CPU); nothing here is compiled, so only the eager flag is set where torch has
    # the call.
    if hasattr(torch._C, "_set_deterministic_algorithms"):
        torch._C._set_deterministic_algorithms(True, warn_only=True)
    else:
        torch.use_deterministic_algorithms(True, warn_only=True)
    torch.utils.deterministic.fill_uninitialized_memory = False


def seed_everything(seed: int) -> None:
    """Seed Python's, numpy's and torch's global generators and make torch deterministic."""
    import numpy as np  # here, not at the top: `import dynslam_cli` imports this module and must stay light
    import torch

    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)
    deterministic_torch()


def set_threads(n: int) -> int:
    """Torch's and numba's thread counts (``n`` <= 0: all cores); returns the count."""
    import torch

    n = int(n) if n and n > 0 else (os.cpu_count() or 1)
    torch.set_num_threads(n)
    try:
        import numba

        choose_numba_layer()  # set_num_threads starts numba's pool: the layer must be chosen first
        numba.set_num_threads(min(n, numba.config.NUMBA_NUM_THREADS))
    except Exception:  # numba absent or threads fixed: the torch setting still holds
        pass
    return n


def same_torch_threads(n: int) -> None:
    """A worker thread's initializer: its torch thread count (OpenMP and MKL keep one per thread) set to
    ``n``, its creator's.  Torch gives a new thread its count lazily, at its first parallel operation,
    from the process's count at that moment; the classifier lowers that to 1 while its tiny MLP runs
    (``motion/classifier._few_threads``), so a worker whose first operation fell then would run, and
    sum, on one thread for good, and a run's bits would depend on that timing (docs/experiments.md,
    "A mapping thread")."""
    import torch

    torch.get_num_threads()  # torch's lazy initialisation of this thread, now
    torch.set_num_threads(n)
