"""Argument groups a Python caller passes to the compiled kernels, sized for numba's dispatch.

Numba's dispatcher finds the types of a call's arguments through a cache keyed by a
*fingerprint* of each argument: an array takes 8 bytes, a tuple 2 bytes plus its items', a
None, int, float or bool 1 byte. In numba 0.56 a fingerprint longer than
:data:`FINGERPRINT_BYTES` loses its first bytes (the buffer that outgrows its preallocated
40 bytes is allocated without copying them), so the cache misses at random: the call then
types its arguments in Python, 40-500 us instead of a few, and each miss adds a cache entry
that is never freed. A tuple of five arrays (42 bytes) is past the limit.

Every argument a Python caller passes to a kernel therefore fits (:func:`fits`): groups of
at most four arrays (with a few scalars or Nones), which the kernels join into their larger
groups in compiled code (:func:`joined`, :func:`in_place`), where tuples cost nothing.
"""

from __future__ import annotations

from numba import types
from numba._dispatcher import compute_fingerprint
from numba.extending import overload

FINGERPRINT_BYTES = 40  # the longest argument fingerprint numba 0.56's type cache keeps intact


def fits(value) -> bool:
    """Whether numba's dispatch caches the type of the argument ``value`` by an intact
    fingerprint (at most :data:`FINGERPRINT_BYTES`)."""
    return len(compute_fingerprint(value)) <= FINGERPRINT_BYTES


def joined(head, tail):
    """In compiled code: ``head + tail`` (tuples), None if ``head`` is None (an optional group
    and its optional continuation, e.g. the volume term's arrays and its checks)."""
    raise NotImplementedError("joined is for compiled code")


@overload(joined)
def _joined(head, tail):
    if isinstance(head, types.NoneType):
        return lambda head, tail: None
    return lambda head, tail: head + tail


def in_place(arms):
    """In compiled code: the Maxwell arms' kernel tuple ``(r, c, prev, strain_prev, out,
    strain_out)`` whose outputs are its inputs, from ``arms`` = (r, c, prev, strain_prev)
    (:mod:`particle.volume`); None for None."""
    raise NotImplementedError("in_place is for compiled code")


@overload(in_place)
def _in_place(arms):
    if isinstance(arms, types.NoneType):
        return lambda arms: None
    return lambda arms: (arms[0], arms[1], arms[2], arms[3], arms[2], arms[3])
