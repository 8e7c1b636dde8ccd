"""Thread count of the compiled kernels, and the threading layer they run on.

:func:`numba_threads` sets how many threads the enclosed ``parallel=True`` kernels (neighbour
index and moments, normals, FPFH, ICP and GICP sums) run on. Their ``numba.prange`` loops run
over fixed chunks of rows, each in its own fixed order, so the count changes the speed, never
the bits.

Importing this module also picks numba's threading layer (OpenMP first) and lets idle OpenMP
threads sleep (``OMP_WAIT_POLICY=PASSIVE`` unless the user set it). Both are read when the first
parallel kernel starts: every module whose functions launch kernels imports this one (directly
or through :mod:`spacepose.core.grid`), so the settings are in place by then.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager

import numba
import numpy as np

from spacepose.errors import InputError

# OpenMP before TBB: Open3D (the optional peer) bundles a TBB older than numba accepts, and the
# OpenMP layer, unlike the workqueue fallback, takes concurrent calls from several threads.
numba.config.THREADING_LAYER_PRIORITY = ["omp", "tbb", "workqueue"]
# Idle OpenMP threads sleep instead of spinning: after a short kernel a spinning thread takes a
# core from the work that follows (a lab tracking step interleaved with Open3D took 80 ms instead
# of 27 on two cores). Read when the OpenMP runtime starts; a user's own setting wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def thread_count(workers: int) -> int:
    """The threads ``workers`` asks for (-1: all cores), at most the cores numba has.

    Raises
    ------
    InputError
        Neither -1 nor a positive integer (a stateful user, the tracker, checks it when built:
        a run's outputs are not started on a count its first kernel would refuse).
    """
    available = numba.config.NUMBA_NUM_THREADS
    if workers == -1:
        return available
    if isinstance(workers, int | np.integer) and not isinstance(workers, bool) and workers >= 1:
        return min(int(workers), available)
    raise InputError(f"workers must be -1 (all cores) or a positive count, got {workers!r}")


@contextmanager
def numba_threads(workers: int) -> Iterator[None]:
    """Run the enclosed kernels on ``workers`` threads (-1: all cores), then restore the count."""
    count = thread_count(workers)
    before = numba.get_num_threads()
    numba.set_num_threads(count)
    try:
        yield
    finally:
        numba.set_num_threads(before)
