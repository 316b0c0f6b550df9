"""A compile-time fix for the installed numba (Debian's 0.56) that later numba releases carry.

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
"""
from __future__ import annotations

import copy

import numba
from numba.core import ir

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


def install() -> None:
    """Give ``ir.Var`` the location-sharing deep copy where numba lacks it (idempotent).
    Runs when this module is imported: :mod:`particle` imports it first."""
    if needed():
        ir.Var.__deepcopy__ = _var_deepcopy


install()
