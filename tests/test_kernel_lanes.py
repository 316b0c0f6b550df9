"""The lane-wise (SIMD) connector and tet passes against their scalar loops, bit for bit.

:func:`particle.kernels.add_connector_forces` and :func:`particle.volume.add_volume_forces`
take their items ``LANES`` at a time; a range shorter than ``LANES`` goes through the scalar
loop. Calling them item by item in order is therefore the scalar reference: the same
additions into the force array in the same order, so forces, arm states, elongations,
the first connector / tet outside its range and that tet's volume must be identical, not
close (and :func:`particle.volume.first_volume_outside`, the final-state check, must name
the same tet). Checked on a box mesh in its own connector order and shuffled (ends swapped too: no
order is assumed), linear / nonlinear springs, with and without arms, and for arrays that
are not C-contiguous (the lanes' element-wise loads).
"""
from __future__ import annotations

import numpy as np
import pytest

from particle import kernels
from particle.lanes import LANES
from particle.volume import add_volume_forces, first_volume_outside
from tests.particle_models import box_model

RNG_SEED = 7


def _connector_case(shuffled: bool):
    """(x, edges, rest lengths, K0, a, b, arm r, arm c, arm forces, elongations) of a
    deformed 4x4x3 box with random arm states; 467 connectors (not a multiple of LANES)."""
    rng = np.random.default_rng(RNG_SEED)
    model = box_model((4, 4, 3))
    edges = model.edges.copy()
    if shuffled:
        edges = edges[rng.permutation(len(edges))]
        swap = rng.random(len(edges)) < 0.5
        edges[swap] = edges[swap][:, ::-1]
    n = len(edges)
    x = model.rest_positions + 2e-3 * rng.standard_normal(model.rest_positions.shape)
    rest = np.linalg.norm(model.rest_positions[edges[:, 1]] - model.rest_positions[edges[:, 0]],
                          axis=1)
    return (x, edges, rest, rng.uniform(20, 40, n), rng.uniform(-30, 30, n),
            rng.uniform(0, 400, n), rng.uniform(0.5, 1.0, (n, 2)), rng.uniform(1, 20, (n, 2)),
            1e-2 * rng.standard_normal((n, 2)), 1e-3 * rng.standard_normal(n))


def _connector_pass(case, nonlinear, arms, limits, first, stop, one_by_one):
    """forces, arm forces, elongations and the first connector outside ``limits`` after the
    connectors ``first .. stop-1``, in one call or one call per connector."""
    x, edges, rest, K0, a, b, r, c, arm, dx = case
    forces, arm, dx = np.zeros_like(x), arm.copy(), dx.copy()
    a, b = (a, b) if nonlinear else (None, None)
    r, c = (r, c) if arms else (None, None)
    lo, hi = limits if limits is not None else (None, None)
    spans = [(e, e + 1) for e in range(first, stop)] if one_by_one else [(first, stop)]
    outside = -1
    for start, end in spans:
        found = kernels.add_connector_forces(x, edges, rest, K0, a, b, r, c, arm, dx, forces,
                                             None, arm, dx, lo, hi, start, end)
        if outside < 0:
            outside = found
    return forces, arm, dx, outside


@pytest.mark.parametrize("shuffled", [False, True], ids=["mesh order", "shuffled"])
@pytest.mark.parametrize("nonlinear, arms", [(False, True), (True, False), (True, True)])
@pytest.mark.parametrize("first, stop", [(0, None), (3, -2)])
def test_the_connector_lanes_equal_the_scalar_loop_bit_for_bit(shuffled, nonlinear, arms, first,
                                                                stop):
    case = _connector_case(shuffled)
    stop = len(case[1]) + (stop or 0)
    assert (stop - first) % LANES != 0  # a scalar remainder too
    lanes = _connector_pass(case, nonlinear, arms, None, first, stop, one_by_one=False)
    scalar = _connector_pass(case, nonlinear, arms, None, first, stop, one_by_one=True)
    for got, want in zip(lanes, scalar):
        np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("bad", [[1], [6, 2], [200], [465]], ids=["lane", "two", "late", "rest"])
def test_the_connector_lanes_report_the_first_connector_outside_its_range(bad):
    """A NaN bound, or a bound the elongation violates, marks a connector as outside; the
    lanes report the first in connector order (465: the scalar remainder)."""
    case = _connector_case(False)
    n = len(case[1])
    lo, hi = np.full(n, -1.0), np.full(n, 1.0)
    lo[bad[0]] = np.nan
    hi[bad[1:]] = -1.0
    lanes = _connector_pass(case, False, True, (lo, hi), 0, n, one_by_one=False)
    scalar = _connector_pass(case, False, True, (lo, hi), 0, n, one_by_one=True)
    assert lanes[3] == scalar[3] == min(bad)
    assert _connector_pass(case, False, True, (np.full(n, -1.0), hi * 0 + 1.0), 0, n,
                           one_by_one=False)[3] == -1


def test_the_lanes_load_arrays_that_are_not_contiguous_element_by_element():
    """Fortran-ordered positions and arm arrays, strided per-connector arrays: the same
    result as C-contiguous copies."""
    x, edges, rest, K0, a, b, r, c, arm, dx = _connector_case(True)

    def strided(v):
        out = np.empty((2,) + v.shape)
        out[0] = v
        return out[0] if v.ndim > 1 else np.repeat(v, 2)[::2]

    case = (x, edges, rest, K0, a, b, r, c, arm, dx)
    odd = (np.asfortranarray(x), np.asfortranarray(edges), strided(rest), strided(K0),
           strided(a), strided(b), np.asfortranarray(r), np.asfortranarray(c), arm, dx)
    assert not odd[2].flags.c_contiguous and not odd[0].flags.c_contiguous
    want = _connector_pass(case, True, True, None, 0, len(edges), one_by_one=False)
    got = _connector_pass(odd, True, True, None, 0, len(edges), one_by_one=False)
    for g, w in zip(got, want):
        np.testing.assert_array_equal(g, w)


def _volume_case():
    """(x, tets, rest volumes, kv, v_lo, v_hi, arm r, arm c, pressures, strains) of a deformed
    4x4x3 box (288 tets, shuffled, a multiple of LANES: one tet dropped for a remainder).

    Typed as a run passes them (tets an unsigned index view, tets, rest volumes and kv
    read-only), so these calls share the compiled pass of the runs (each other typing
    of the tet pass costs ~4 s of compilation)."""
    rng = np.random.default_rng(RNG_SEED)
    model = box_model((4, 4, 3))
    tets = kernels.index_view(np.ascontiguousarray(model.tets[rng.permutation(model.n_tets)][1:]))
    t = len(tets)
    x = model.rest_positions + 5e-4 * rng.standard_normal(model.rest_positions.shape)
    rest, kv = np.full(t, model.rest_volumes.mean()), rng.uniform(5e3, 1e4, t)
    for fixed in (tets, rest, kv):
        fixed.flags.writeable = False
    return (x, tets, rest, kv, np.zeros(t), np.full(t, 1.0),
            rng.uniform(0.5, 1.0, (t, 2)), rng.uniform(1e3, 2e3, (t, 2)),
            rng.standard_normal((t, 2)), 1e-2 * rng.standard_normal(t))


def _volume_pass(case, arms, v_lo, v_hi, one_by_one):
    """forces, arm pressures, strains, volumes, (first bad tet, its volume) after every tet, in
    one call or one call per tet."""
    x, tets, rest, kv, _, _, r, c, pressure, strain = case
    forces, pressure, strain = np.zeros_like(x), pressure.copy(), strain.copy()
    volumes = np.empty(len(tets))
    spans = ([slice(t, t + 1) for t in range(len(tets))] if one_by_one
             else [slice(0, len(tets))])
    bad = (-1, 0.0)
    for s in spans:
        arm_tuple = None if not arms else (r[s], c[s], pressure[s], strain[s], pressure[s],
                                           strain[s])
        found, volume = add_volume_forces(x, tets[s], rest[s], kv[s], v_lo[s], v_hi[s], forces,
                                          arm_tuple, volumes[s])
        if bad[0] < 0 and found >= 0:
            bad = (found + s.start, volume)
    return forces, pressure, strain, volumes, bad


@pytest.mark.parametrize("arms", [False, True], ids=["elastic", "viscoelastic"])
@pytest.mark.parametrize("bad", [[], [9], [130, 40], [286]], ids=["none", "lane", "two", "rest"])
def test_the_tet_lanes_equal_the_scalar_loop_bit_for_bit(arms, bad):
    case = _volume_case()
    t = len(case[1])
    assert t % LANES != 0
    v_lo, v_hi = case[4].copy(), case[5].copy()
    if bad:
        v_lo[bad[0]] = np.nan  # NaN: outside
        v_hi[bad[1:]] = 0.0
    assert _volume_pass(case, arms, case[4], case[5], one_by_one=False)[4][0] == -1
    lanes = _volume_pass(case, arms, v_lo, v_hi, one_by_one=False)
    scalar = _volume_pass(case, arms, v_lo, v_hi, one_by_one=True)
    for got, want in zip(lanes[:4], scalar[:4]):
        np.testing.assert_array_equal(got, want)
    assert lanes[4] == scalar[4]
    assert lanes[4][0] == (min(bad) if bad else -1)
    # a run's final-state check finds the same tet
    assert first_volume_outside(case[0], case[1], v_lo, v_hi) == lanes[4][0]
