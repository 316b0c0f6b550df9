"""Threads of the BLAS numpy calls, changed for a block of code.

Processes run with ``OMP_NUM_THREADS=1`` (Makefile): the calibration workers and
MPI ranks own one core each. A phase where the workers wait for the parent's
dense algebra (the gradient fit's Woodbury products between two Jacobians)
leaves those cores idle; :func:`blas_threads` lends them to the parent's BLAS for
that phase (a ``with`` block, or a decorator of the function that does it). It
acts on OpenBLAS (Debian's ``libblas.so.3`` alternative); with another BLAS, or
where the loaded libraries cannot be listed, it does nothing.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import os
from typing import Callable, Iterator

import numpy as np  # noqa: F401  (loads the BLAS this module looks for)


@functools.lru_cache(maxsize=1)
def _openblas() -> tuple[Callable[[], int], Callable[[int], None]] | None:
    """(get, set) of the loaded OpenBLAS's thread count, or None."""
    try:
        with open("/proc/self/maps") as maps:
            paths = sorted({line.split()[-1] for line in maps
                            if "blas" in line and line.split()[-1].startswith("/")})
    except OSError:
        return None
    for path in paths:
        try:
            lib = ctypes.CDLL(path)
            get, put = lib.openblas_get_num_threads, lib.openblas_set_num_threads
        except (OSError, AttributeError):
            continue
        get.restype, put.argtypes = ctypes.c_int, [ctypes.c_int]
        return get, put
    return None


def available_cores() -> int:
    """Cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


@contextlib.contextmanager
def blas_threads(n: int | None = None) -> Iterator[None]:
    """Run the block with ``n`` BLAS threads (at most, and by default, the available cores),
    then restore."""
    calls = _openblas()
    if calls is None:
        yield
        return
    get, put = calls
    before = get()
    put(max(1, available_cores() if n is None else min(n, available_cores())))
    try:
        yield
    finally:
        put(before)
