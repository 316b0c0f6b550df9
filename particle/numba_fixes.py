"""Compile time of the installed numba (Debian's 0.56): a fix later releases carry, and the
cyclic garbage collector held back while numba compiles.

**Inlining copies every source line, many times.** Numba inlines an ``inline="always"``
function (the tet pass's lanes, :func:`particle.volume.tet_lanes`) by deep-copying the
callee's IR statement by statement. A variable's deep copy copies its scope, with every
variable of the function, and each variable's source location, which caches the lines of
its whole source file. Each statement's copy is thus the size of the function times its
file, and most of a kernel's cold compilation went into ``copy.deepcopy``. Numba 0.59
gives ``ir.Var`` a deep copy that shares its location (a location is never changed
after it is made); :func:`install` gives the same to older numba.

The compiled machine code is the same (the tet pass's assembly compared with and without
it: equal but for the address of an error-message constant). Measured on an empty cache,
one core: the tet pass 4.4 -> 2.2 s of compilation, the static Newton loop
(:mod:`particle.statics_kernels`) 17.4 -> 12.4 s.

**The cyclic collector runs thousands of times per compilation.** A compilation allocates
millions of short-lived IR and llvmlite objects, and Python's collector examines its
youngest generation every :data:`DEFAULT_GEN0` net allocations. While numba compiles (from
the start of the outermost ``numba:compile`` event to its end) the threshold is
:data:`COMPILE_GEN0`, then set back to what it was; what is allocated meanwhile is still
collected, in fewer, larger passes. Nothing compiled changes. Measured on an empty cache,
one core, three runs each: the static Newton loop 14.7-15.2 -> 13.8-14.1 s of compilation,
the explicit loop with arms 2.82-3.08 -> 2.66-2.75 s; the Newton loop's peak memory 258 ->
286 MB with a threshold of 10,000 (500 MB with the collector off).
"""
from __future__ import annotations

import copy
import gc
import threading

import numba
from numba.core import event, ir

FIXED_IN = (0, 59)  # the first numba release whose ir.Var shares its location on deep copy


def _var_deepcopy(self: ir.Var, memo: dict) -> ir.Var:
    """A deep copy of the variable ``self`` with its scope copied (through ``memo``) and its
    location shared."""
    copied = ir.Var(copy.deepcopy(self.scope, memo), self.name, self.loc)
    memo[id(self)] = copied
    return copied


def needed(version: tuple[int, ...] = numba.version_info[:2]) -> bool:
    """Whether numba ``version`` copies a variable's location on deep copy (before 0.59,
    unless it defines its own ``ir.Var.__deepcopy__``)."""
    return tuple(version) < FIXED_IN and "__deepcopy__" not in vars(ir.Var)


DEFAULT_GEN0 = 700  # Python's own youngest-generation threshold
COMPILE_GEN0 = 10_000  # the threshold while numba compiles


class CollectorThreshold(event.Listener):
    """Listener of ``numba:compile``: the youngest generation's threshold is ``gen0`` from
    the start of the outermost compilation (nested ones are the callees it compiles) to its
    end, and the caller's threshold before and after."""

    def __init__(self, gen0: int = COMPILE_GEN0):
        self.gen0 = gen0
        self._depth = 0
        self._saved: tuple[int, ...] | None = None
        self._lock = threading.Lock()

    def on_start(self, ev) -> None:
        with self._lock:
            self._depth += 1
            if self._depth == 1:
                self._saved = gc.get_threshold()
                gc.set_threshold(max(self.gen0, self._saved[0]), *self._saved[1:])

    def on_end(self, ev) -> None:
        with self._lock:
            self._depth -= 1
            if self._depth == 0 and self._saved is not None:
                gc.set_threshold(*self._saved)
                self._saved = None


_threshold: CollectorThreshold | None = None


def install() -> None:
    """Give ``ir.Var`` the location-sharing deep copy where numba lacks it, and register
    :class:`CollectorThreshold` (both idempotent). Runs when this module is imported:
    :mod:`particle` imports it first."""
    global _threshold
    if needed():
        ir.Var.__deepcopy__ = _var_deepcopy
    if _threshold is None:
        _threshold = CollectorThreshold()
        event.register("numba:compile", _threshold)


install()
