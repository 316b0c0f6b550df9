"""The per-tet volume term (particle/volume.py): closed forms, twins, tangent, stability, refusals."""
import dataclasses
import re

import numpy as np
import pytest
import scipy.sparse as sp

from forcecal.errors import MeshError, ParameterError, StabilityError
from particle import kernels
from particle.evaluators import IndentationEvaluator, RelaxationEvaluator
from particle.integrator import VerletIntegrator
from particle.experiments import release_ranges
from particle.stability import (critical_time_step, release_volume_range, step_bound,
                                strain_range_for_release)
from particle.model import ModelBuilder, Prescribed
from particle.reference_numpy import step_numpy
from particle.statics import EquilibriumSolver, TangentPattern, gravity_static, tangent_data
from particle.params import viscoelastic_params
from tests.particle_models import (box_model, compiled_and_numpy_steps, haptic_push,
                                   spring_energy, top_centre, volume_pass)
from particle.volume import (add_volume_tangent, add_volume_tangent_numpy,
                             network_bulk_modulus, signed_volumes, signed_volumes_numpy,
                             volume_arm_pressures_numpy,
                             volume_energy, volume_forces_numpy, volume_hessian_numpy,
                             volume_kv_sensitivity_numpy, volume_ratio_range, volume_strains)
from pipelines.bench.empirical_limit import bisect, blows_up

GRAVITY = np.array([0.0, 0.0, -9.81])
ELASTIC = dict(g=(1e-12, 1e-12))  # arms of negligible stiffness: a purely elastic model
TET = np.array([[0.0, 0.0, 0.0], [0.02, 0.0, 0.0], [0.003, 0.018, 0.0], [0.004, 0.006, 0.017]])


def with_kv(model, kv, arms=None, tau=(0.05, 0.5)):
    """The model with a volume stiffness kv [Pa] on every tet, elastic, or with Maxwell arms of
    stiffnesses ``arms`` (kv1, kv2) [Pa] and relaxation times ``tau`` [s]."""
    t = model.n_tets
    volume = {"kv": np.full(t, kv)}
    if arms is not None:
        volume.update(kv1=np.full(t, arms[0]), bv1=np.full(t, arms[0] * tau[0]),
                      kv2=np.full(t, arms[1]), bv2=np.full(t, arms[1] * tau[1]))
    return model.with_params(dataclasses.replace(model.params, **volume))


#: the elastic volume term and the relaxing one (arms kv1, kv2 [Pa])
VOLUME_TERMS = pytest.mark.parametrize("arms", [None, (1500.0, 1000.0)],
                                       ids=["elastic", "viscoelastic"])


def single_tet(kv=1000.0, K0=1e-9, fixed=(False,) * 4):
    """One tet (edges as connectors, springs negligible unless K0 is given)."""
    builder = ModelBuilder()
    builder.add_particles(TET, np.full(4, 1e-3), np.array(fixed))
    builder.add_connectors([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
    params = dataclasses.replace(viscoelastic_params(6, K0, **ELASTIC), kv=np.array([kv]))
    return builder.finalize(params, tets=np.array([[0, 1, 2, 3]]))


def deformed(model, amplitude=1e-3, seed=0):
    rng = np.random.default_rng(seed)
    return model.rest_positions + amplitude * rng.standard_normal(model.rest_positions.shape)


def test_uniform_dilation_of_one_tet_gives_the_closed_form_force_and_energy():
    """x -> c + s (x - c): V/V0 = s^3, f_a = -kv (s^3 - 1) s^2 g0_a with g0_a the rest gradient
    (|g0_a| = area of the opposite face / 3), E = kv/2 V0 (s^3 - 1)^2. Round-off only."""
    kv = 2500.0
    model = single_tet(kv)
    v0 = model.rest_volumes[0]
    assert v0 == pytest.approx(abs(np.linalg.det(TET[1:] - TET[0])) / 6, rel=1e-14)
    g0 = volume_forces_numpy(TET + 0.0, model.tets, model.rest_volumes, np.array([1.0]))
    assert np.allclose(g0, 0.0)  # at rest: no force
    centre = TET.mean(axis=0)
    for s in (0.9, 0.99, 1.01, 1.2):
        x = centre + s * (TET - centre)
        f = np.zeros((4, 3))
        assert volume_pass(x, model.tets, model.rest_volumes, model.params.kv, f)[0] == -1
        # the rest gradients: each vertex's opposite face normal (area vector)/3, inward
        grad_rest = np.array([np.cross(TET[3] - TET[1], TET[2] - TET[1]),
                              np.cross(TET[2] - TET[0], TET[3] - TET[0]),
                              np.cross(TET[3] - TET[0], TET[1] - TET[0]),
                              np.cross(TET[1] - TET[0], TET[2] - TET[0])]) / 6.0
        expect = -kv * (s ** 3 - 1.0) * s ** 2 * grad_rest
        np.testing.assert_allclose(f, expect, rtol=1e-12, atol=1e-14 * np.abs(expect).max())
        energy = volume_energy(x, model.tets, model.rest_volumes, model.params.kv)
        assert energy == pytest.approx(0.5 * kv * v0 * (s ** 3 - 1) ** 2, rel=1e-12)
    # small strain: the term adds exactly kv to the bulk modulus, E/V0 = 9/2 kv eps^2
    eps = 1e-6
    x = centre + (1 + eps) * (TET - centre)
    assert volume_energy(x, model.tets, model.rest_volumes, model.params.kv) / v0 == \
        pytest.approx(4.5 * kv * eps ** 2, rel=1e-5)


def test_forces_are_minus_the_energy_gradient_and_numba_matches_numpy():
    """Central differences of the energy (O(h^2) error, h = 1e-7 m: ~1e-7 relative) and the
    numpy twin (same formulas: round-off) on a randomly deformed box."""
    model = with_kv(box_model((2, 2, 2), fixed_bottom=False), 3000.0)
    x = deformed(model, 5e-4)
    kv = model.params.kv
    numba = np.zeros_like(x)
    assert volume_pass(x, model.tets, model.rest_volumes, kv, numba)[0] == -1
    twin = volume_forces_numpy(x, model.tets, model.rest_volumes, kv)
    np.testing.assert_allclose(numba, twin, rtol=0, atol=1e-13 * np.abs(twin).max())
    fd = -central_gradient(lambda y: volume_energy(y, model.tets, model.rest_volumes, kv), x)
    np.testing.assert_allclose(numba, fd, rtol=0, atol=1e-6 * np.abs(fd).max())


def test_compiled_signed_volumes_match_their_numpy_twin():
    """Random tets over positions spread across six orders of magnitude, both orientations,
    int64 and int32 indices: the compiled pass equals the numpy expressions to round-off
    (1e-14 of the scale of its terms; bitwise on the machines measured)."""
    rng = np.random.default_rng(4)
    x = rng.standard_normal((400, 3)) * np.exp(2.0 * rng.standard_normal((400, 3)))
    tets = rng.integers(0, 400, (3000, 4))
    scale = np.prod(np.abs(x[tets]).max(axis=1), axis=1)
    for t in (tets, tets.astype(np.int32)):
        got, want = signed_volumes(x, t), signed_volumes_numpy(x, t)
        assert got.dtype == np.float64 and got.shape == (3000,)
        assert np.all(np.abs(got - want) <= 1e-14 * scale)
    assert np.any(signed_volumes(x, tets) < 0) and np.any(signed_volumes(x, tets) > 0)


def test_the_kv_sensitivity_is_the_force_per_unit_kv():
    """Forces are linear in kv: the sensitivity of each tet times its kv sums to the forces."""
    model = with_kv(box_model((2, 2, 2), fixed_bottom=False), 3000.0)
    x = deformed(model, 5e-4, seed=7)
    sens = volume_kv_sensitivity_numpy(x, model.tets, model.rest_volumes)
    f = np.zeros_like(x)
    np.add.at(f, model.tets.ravel(), (model.params.kv[:, None, None] * sens).reshape(-1, 3))
    twin = volume_forces_numpy(x, model.tets, model.rest_volumes, model.params.kv)
    np.testing.assert_allclose(f, twin, rtol=0, atol=1e-13 * np.abs(twin).max())


def test_the_static_tangent_with_the_volume_term_is_the_derivative_of_the_forces():
    """The assembled CSC tangent (springs + volume, nonlinear springs, fixed bottom) against
    central differences of the compiled forces (forces are smooth: O(h^2) ~ 1e-8 relative),
    and one tet's block against the numpy Hessian."""
    model = box_model((2, 2, 2), a=-20.0, b=300.0)
    model = with_kv(model, 4000.0)
    x = deformed(model, 5e-4, seed=3)
    tangent, fd = tangent_and_differences(model, x)
    np.testing.assert_allclose(tangent, fd, rtol=0, atol=1e-6 * np.abs(fd).max())
    # the volume term alone, one tet, numpy Hessian vs central differences of its forces
    tet = single_tet(4000.0)
    xt = deformed(tet, 2e-3, seed=5)
    hess = volume_hessian_numpy(xt, tet.tets[0], tet.rest_volumes[0], 4000.0)
    fd = np.empty((12, 12))
    for k in range(12):
        xp, xm = xt.copy(), xt.copy()
        xp.ravel()[k] += 1e-8
        xm.ravel()[k] -= 1e-8
        fd[:, k] = -(volume_forces_numpy(xp, tet.tets, tet.rest_volumes, tet.params.kv)
                     - volume_forces_numpy(xm, tet.tets, tet.rest_volumes,
                                           tet.params.kv)).ravel() / 2e-8
    np.testing.assert_allclose(hess, fd, rtol=0, atol=1e-6 * np.abs(fd).max())
    np.testing.assert_allclose(hess, hess.T, atol=1e-12 * np.abs(hess).max())


def central_gradient(energy, x, h=1e-7):
    """(N, 3) central differences (step ``h`` [m]) of the scalar ``energy(x)`` [J] at ``x``
    (N, 3) [m]."""
    grad = np.empty_like(x)
    for n in range(x.shape[0]):
        for c in range(3):
            xp, xm = x.copy(), x.copy()
            xp[n, c] += h
            xm[n, c] -= h
            grad[n, c] = (energy(xp) - energy(xm)) / (2 * h)
    return grad


def tangent_and_differences(model, x, arms=None, h=1e-8):
    """(the assembled static tangent (n, n) [N/m] on the free dofs at ``x`` (N, 3), fixed
    particles put at rest, with the arm step ``arms`` (None: long-term), and its central
    differences of the statics' forces (step ``h`` [m]))."""
    p = model.params
    x = x.copy()
    x[model.fixed] = model.rest_positions[model.fixed]
    solver = EquilibriumSolver(model, np.zeros(0, np.int64), TangentPattern.of(model))
    it = solver._evaluate(x, p, True, arms, None)
    pat = solver.pattern
    data = tangent_data(model, pat, x, it.tension, p, True, arms, it.volume_arm)
    tangent = sp.csc_matrix((data, pat.indices, pat.indptr),
                            shape=(pat.n_dofs, pat.n_dofs)).toarray()
    free = model.free_nodes
    fd = np.empty((3 * len(free), 3 * len(free)))
    for k, n in enumerate(free):
        for c in range(3):
            xp, xm = x.copy(), x.copy()
            xp[n, c] += h
            xm[n, c] -= h
            df = (solver._evaluate(xp, p, True, arms, None).forces
                  - solver._evaluate(xm, p, True, arms, None).forces)[free].ravel() / (2 * h)
            fd[:, 3 * k + c] = -df
    return tangent, fd


def random_tets(n_tets, rng):
    """Disjoint tets (``TET`` perturbed, positively oriented, 0.1 m off the origin, about 1 in 4
    particles fixed, kv 1-10 kPa) and positions where they are, in turn, randomly deformed,
    compressed (V/V0 ~ 0.05), inverted (one vertex mirrored through its opposite face) and
    stretched (V/V0 ~ 4)."""
    rest = TET + 0.1 + 3e-3 * rng.standard_normal((n_tets, 4, 3))
    flip = signed_volumes(rest.reshape(-1, 3), np.arange(4 * n_tets).reshape(-1, 4)) < 0
    rest[flip, 2:] = rest[flip, 3:1:-1]
    builder = ModelBuilder()
    builder.add_particles(rest.reshape(-1, 3), np.full(4 * n_tets, 1e-3),
                          rng.random(4 * n_tets) < 0.25)
    tets = np.arange(4 * n_tets).reshape(-1, 4)
    builder.add_connectors(tets[:, [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]])
    params = dataclasses.replace(viscoelastic_params(6 * n_tets),
                                 kv=rng.uniform(1e3, 1e4, n_tets))
    model = builder.finalize(params, tets=tets)
    x = rest + 1e-3 * rng.standard_normal(rest.shape)
    centre = x.mean(axis=1, keepdims=True)
    x[1::4] = centre[1::4] + 0.37 * (x[1::4] - centre[1::4])
    x[3::4] = centre[3::4] + 1.6 * (x[3::4] - centre[3::4])
    face = x[2::4, :3]
    normal = np.cross(face[:, 1] - face[:, 0], face[:, 2] - face[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    height = np.einsum("ij,ij->i", x[2::4, 3] - face[:, 0], normal)
    x[2::4, 3] -= 2.0 * height[:, None] * normal
    return model, x.reshape(-1, 3)


def test_the_closed_form_tangent_kernel_equals_its_numpy_twin():
    """add_volume_tangent (closed-form d^2V/dp_a dp_b) against add_volume_tangent_numpy (per
    tet volume_hessian_numpy: d^2V from unit displacements) added onto random data: random
    disjoint tets (deformed, compressed, inverted, stretched; fixed particles: -1 slots) and
    a randomly deformed box with its bottom fixed (tets sharing particles). Round-off only:
    within 1e-12 of the largest entry (measured 4e-16)."""
    rng = np.random.default_rng(11)
    box = with_kv(box_model((3, 3, 2)), 4000.0)
    cases = [random_tets(48, rng), (box, deformed(box, 2e-3, seed=2))]
    ratio = signed_volumes(cases[0][1], cases[0][0].tets) / cases[0][0].rest_volumes
    assert ratio[2::4].max() < 0 and 0 < ratio[1::4].max() < 0.1 and ratio[3::4].min() > 2
    for model, x in cases:
        slots = TangentPattern.of(model).tet_slots
        assert (slots < 0).any() and (slots >= 0).any()
        nnz = int(slots.max()) + 1
        args = (x, model.tets, model.rest_volumes, model.params.kv, slots)
        reference = np.zeros(nnz)
        add_volume_tangent_numpy(*args, reference)
        start = rng.standard_normal(nnz) * np.abs(reference).max()
        compiled, twin = start.copy(), start.copy()
        add_volume_tangent(*args, compiled, None)
        add_volume_tangent_numpy(*args, twin)
        np.testing.assert_allclose(compiled, twin, rtol=0,
                                   atol=1e-12 * np.abs(reference).max())
        alone = np.zeros(nnz)
        add_volume_tangent(*args, alone, None)
        np.testing.assert_allclose(alone, reference, rtol=0,
                                   atol=1e-12 * np.abs(reference).max())


@VOLUME_TERMS
def test_compiled_step_with_the_volume_term_matches_the_numpy_step(arms):
    """All terms (nonlinear springs, arms, gravity, damping, a prescribed particle) + volume
    (elastic or relaxing): same formulas, same order, round-off only (as the springs-only twin
    test), the volume arms' pressures and strains too."""
    model = with_kv(box_model(a=-20.0, b=300.0), 2000.0, arms)
    compiled, reference, _ = compiled_and_numpy_steps(model, GRAVITY)
    scale = np.abs(reference.x - model.rest_positions).max()
    np.testing.assert_allclose(compiled.x, reference.x, rtol=0, atol=1e-12 * scale)
    if arms is not None:
        pressure = np.abs(reference.volume_arm).max()
        assert pressure > 0
        np.testing.assert_allclose(compiled.volume_arm, reference.volume_arm, rtol=0,
                                   atol=1e-10 * pressure)
        np.testing.assert_allclose(compiled.volume_prev, reference.volume_prev, rtol=0,
                                   atol=1e-13)


@VOLUME_TERMS
def test_threaded_and_split_runs_with_the_volume_term_match_the_serial_one(arms):
    """Two threads: round-off; a run split in two calls: bit for bit (the state carries the
    arms, the volume term's too, from one call to the next)."""
    model = with_kv(box_model(), 2000.0, arms)
    dt = 0.5 * critical_time_step(model)
    runs = []
    for threads in (1, 2):
        state = model.state()
        VerletIntegrator().simulate(model, state, dt, 200, gravity=GRAVITY, threads=threads)
        runs.append(state)
    scale = np.abs(runs[0].x - model.rest_positions).max()
    np.testing.assert_allclose(runs[1].x, runs[0].x, rtol=0, atol=1e-10 * scale)
    split = model.state()
    for n in (120, 80):
        VerletIntegrator().simulate(model, split, dt, n, gravity=GRAVITY)
    np.testing.assert_array_equal(split.x, runs[0].x)
    if arms is not None:
        np.testing.assert_array_equal(split.volume_arm, runs[0].volume_arm)


def test_an_elastic_tet_vibrates_with_constant_energy():
    """Springs + volume, arms negligible, one fixed face: kinetic + spring + volume energy is
    conserved by position Verlet up to its bounded O((omega dt)^2) error (below 1 % at
    dt = 0.1 x the limit: 2.3 % at 0.2 x, the one free vertex's bound being nearly tight),
    over 20000 steps; and it oscillates (energy moves)."""
    model = single_tet(kv=5000.0, K0=20.0, fixed=(True, True, True, False))
    dt = 0.1 * critical_time_step(model)
    state = model.state()
    state.x[3] += [1e-3, -5e-4, 8e-4]
    state.x_prev[:] = state.x

    def energy(s):
        v = (s.x - s.x_prev) / dt
        mid = [s.x, s.x_prev]
        pot = np.mean([spring_energy(model, y) + volume_energy(y, model.tets, model.rest_volumes,
                                                               model.params.kv) for y in mid])
        return 0.5 * float(np.sum(model.masses[:, None] * v ** 2)) + pot

    integrator = VerletIntegrator()
    integrator.simulate(model, state, dt, 1)
    e0 = energy(state)
    values = []
    for _ in range(200):
        integrator.simulate(model, state, dt, 100)
        values.append(energy(state))
    assert np.max(np.abs(np.array(values) - e0)) < 1e-2 * e0
    assert e0 > 0


@pytest.mark.parametrize("arms", [None, (0.6, 0.4)], ids=["elastic", "viscoelastic"])
@pytest.mark.parametrize("kv", [2e3, 2e4])
def test_the_stability_bound_with_the_volume_term_is_below_the_bisected_limit(kv, arms):
    """Rigorous: never above the limit found by bisection (3000 steps from a state at rest,
    perturbed by 1e-6 m, 0.1 %). The bound covers every state of its strain range, where
    faces grow by (1 + hi)^2 and |V/V0 - 1| up to (1 + hi)^3 - 1, so on the default range
    +-0.5 it is well below the limit at rest; on a narrow range it must be close to it
    (> 0.5: Irons' element bound of the volume term added to the springs' one). The term
    lowers the bound against springs only, and its arms (``arms`` x kv, whose instantaneous
    stiffness the bound counts) against the elastic term of the same long-term kv."""
    model = with_kv(box_model((3, 3, 2), **ELASTIC), kv,
                    None if arms is None else (arms[0] * kv, arms[1] * kv))
    estimate = critical_time_step(model)
    empirical = bisect(lambda dt: blows_up(model, dt), estimate)
    assert estimate <= empirical
    narrow = critical_time_step(model, strain_range=(-1e-3, 1e-3))
    assert estimate < narrow <= empirical
    assert narrow / empirical > 0.5
    simpler = dataclasses.replace(model.params, kv=None) if arms is None else \
        dataclasses.replace(model.params, kv1=None, bv1=None, kv2=None, bv2=None)
    assert estimate < critical_time_step(model.with_params(simpler))


def test_bad_kv_is_refused_naming_the_tet():
    model = box_model()
    kv = np.full(model.n_tets, 1000.0)
    for bad in (0.0, -1.0, np.nan, np.inf):
        kv_bad = kv.copy()
        kv_bad[7] = bad
        params = dataclasses.replace(model.params, kv=kv_bad)
        with pytest.raises(ParameterError, match=r"tet 7 \(particles [0-9-]+\): volume stiffness"):
            VerletIntegrator().prepare(model.with_params(params), 1e-5)
    with pytest.raises(ParameterError, match="kv has 3 entries but the model has"):
        model.with_params(dataclasses.replace(model.params, kv=np.ones(3)))


def test_a_tet_edge_that_is_no_connector_is_refused():
    builder = ModelBuilder()
    builder.add_particles(TET, np.full(4, 1e-3))
    builder.add_connectors([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3]])
    with pytest.raises(MeshError, match=r"tet 0 \(particles 0-1-2-3\): an edge of the tet is not"):
        builder.finalize(viscoelastic_params(5), tets=np.array([[0, 1, 2, 3]]))


@pytest.mark.parametrize("monitored", [True, False])
def test_a_tet_leaving_its_volume_range_or_inverting_stops_the_run_naming_tet_and_step(monitored):
    """The free vertex driven through its opposite face in 100 steps (prescribed motion): V/V0
    falls linearly, 1 - 2 s/100 after step s. A monitored run stops when V/V0 leaves the
    range its step was verified for ((1 - 0.5)^3 = 0.125 on the default strain range, at
    step 44: 1 - 88/100 = 0.12); an unmonitored one (_check_dt=False) when the tet inverts
    (step 50: V/V0 = 0). StabilityError naming the tet and the step, never NaN."""
    model = single_tet(kv=1000.0, K0=1.0, fixed=(True, True, True, False))
    dt = 0.5 * critical_time_step(model)
    x3 = model.rest_positions[3]
    through = x3 - [0.0, 0.0, 2 * x3[2]]
    motion = Prescribed([3], [0.0, 100 * dt], [[x3], [through]])
    state = model.state()
    expect = (r"tet 0 \(particles 0-1-2-3\) reached volume ratio V/V0 = 0.12 at step 44 .*"
              r"outside \[0.125, 3.375\]" if monitored else
              r"tet 0 \(particles 0-1-2-3\) inverted \(volume ratio V/V0 = [-0-9.e]+ <= 0\) at "
              r"step 50 ")
    with pytest.raises(StabilityError, match=expect):
        VerletIntegrator().simulate(model, state, dt, 200, prescribed=motion,
                                    _check_dt=monitored)
    assert np.all(np.isfinite(state.x))


def test_static_solutions_balance_forces_and_the_volume_term_stiffens_the_sag():
    model = box_model((3, 3, 2), density=1000.0)
    sag = gravity_static(model, GRAVITY)
    stiff = gravity_static(with_kv(model, 5000.0), GRAVITY)
    assert 0 < np.abs(stiff).max() < np.abs(sag).max()
    m = with_kv(model, 5000.0)
    x = m.rest_positions + stiff
    f = np.empty_like(x)
    kernels.internal_forces(x, m.edges, m.rest_lengths, m.params.K0, None, None, None, None,
                            None, None, f, None, np.zeros((m.n_connectors, 2)),
                            np.empty(m.n_connectors))
    f += volume_forces_numpy(x, m.tets, m.rest_volumes, m.params.kv)
    f += m.masses[:, None] * GRAVITY
    weight = m.masses.sum() * 9.81
    assert np.abs(f[m.free_nodes]).max() < 1e-8 * weight


def test_the_volume_term_does_not_relax():
    """Ramp-and-hold at 20 tau2: the relaxation curve's end equals the static (long-term)
    indentation force, springs + volume (the arms have relaxed, the volume term has not), and
    the volume term adds > 10 % to it (it is really there)."""
    model = box_model((3, 3, 2))
    node = top_centre(model)
    normal = np.array([0.0, 0.0, -1.0])
    params = dataclasses.replace(model.params, kv=np.full(model.n_tets, 4000.0))
    depth = 1e-3
    static = IndentationEvaluator(model, [node], normal[None], [depth])
    relax = RelaxationEvaluator(model, [node], normal[None], [0.05, 1.0, 5.0, 10.0],
                                [depth] * 4)
    f_static = static(params)[0, 0]
    f_relax = relax(params)[0]
    # within 1e-5 (measured 9e-6 at 10 s, 3e-6 at 20 s; springs-only 1e-9 at 10 s): with the
    # volume term holding the shape, the internal particles still creep slowly late in the hold
    assert f_relax[-1] == pytest.approx(f_static, rel=2e-5)
    assert f_static > 1.1 * static(model.params)[0, 0]  # +12.6 % from the volume term
    assert f_relax[0] > f_relax[-1]  # the arms still hold force early in the hold


@VOLUME_TERMS
def test_the_haptic_force_includes_the_volume_term(arms):
    """The force returned by a haptic step is minus the net internal force (springs + volume)
    on the tool particle at the step's end, both kinds of arms advanced one step (numpy
    twin), and Run.force_on gives it bit for bit."""
    model = with_kv(box_model(), 3000.0, arms)
    session, node, force = haptic_push(model)
    s = session.state
    x = s.x
    p = model.params
    d = x[model.edges[:, 1]] - x[model.edges[:, 0]]
    length = np.linalg.norm(d, axis=1)
    dx = length - model.rest_lengths
    r, c = p.arm_recursion(session.dt)
    tension = (p.stiffness(dx / model.rest_lengths) * dx
               + (r * s.arm_force + c * (dx - s.dx_prev)[:, None]).sum(axis=1))
    pull = (tension / length)[:, None] * d
    f = np.zeros_like(x)
    np.add.at(f, model.edges[:, 0], pull)
    np.add.at(f, model.edges[:, 1], -pull)
    pressure = None
    if arms is not None:
        vr, vc = p.volume_arm_recursion(session.dt)
        pressure = volume_arm_pressures_numpy(volume_strains(x, model.tets, model.rest_volumes),
                                              vr, vc, s.volume_arm, s.volume_prev).sum(axis=1)
    vol = volume_forces_numpy(x, model.tets, model.rest_volumes, p.kv, pressure)
    np.testing.assert_allclose(force, (f + vol)[node], rtol=1e-9,
                               atol=1e-12 * np.abs(f[node]).max())
    assert np.linalg.norm(vol[node]) > 0.05 * np.linalg.norm(force)
    if arms is not None:  # the arms' share is really there
        elastic = volume_forces_numpy(x, model.tets, model.rest_volumes, p.kv)[node]
        assert np.linalg.norm(vol[node] - elastic) > 0.01 * np.linalg.norm(force)


def test_kv_is_the_added_bulk_modulus_and_the_network_one_is_closed_form():
    """network_bulk_modulus: K0 sum L^2/(9 V) equals the energy of a uniform dilation of the
    spring network per (9/2 eps^2 V) (exactly, up to O(eps))."""
    model = box_model((2, 2, 2), fixed_bottom=False)
    eps = 1e-6
    x = (1 + eps) * model.rest_positions
    energy = spring_energy(model, x)
    volume = float(signed_volumes(model.rest_positions, model.tets).sum())
    kappa = network_bulk_modulus(model, float(model.params.K0[0]))
    assert energy / (4.5 * eps ** 2 * volume) == pytest.approx(kappa, rel=1e-5)


def test_volume_tangent_compiles_its_block_helper_once_and_matches_the_numpy_twin():
    """add_volume_tangent passes each (a, b) block as a (3, 3) view of the slots: called with
    the 16 literal (a, b) pairs, numba compiled its helper 16 times (3.9 s in every fresh
    process). The kernel still equals the plain-numpy twin on a deformed tet, to rounding:
    the twin takes d^2V from unit displacements, exact because dV/dp_a is affine in p_b."""
    import numba

    from particle import volume
    x = np.array([[0.0, 0, 0], [1.1, 0.1, 0], [0.2, 0.9, 0.1], [0.1, -0.1, 1.2]])
    tets = np.array([[0, 1, 2, 3]])
    slots = np.arange(4 * 4 * 9).reshape(1, 4, 4, 3, 3)
    rest, kv = np.array([1.0 / 6.0]), np.array([6.0])
    data, twin = np.zeros(4 * 4 * 9), np.zeros(4 * 4 * 9)
    # compiled here, without the on-disk cache: a kernel loaded from that cache types none
    # of its callees, and the helper would show no signature at all (the blocks come from
    # add_tet_tangent, which the nodal term's tangent shares)
    volume.add_volume_tangent(x, tets, rest, kv, slots, data, None)
    numba.njit(volume.add_tet_tangent.py_func)(x, tets, 0, 1.0, 0.5, ((0.1, 0.2, 0.3),) * 4,
                                               slots, np.zeros(4 * 4 * 9))
    volume.add_volume_tangent_numpy(x, tets, rest, kv, slots, twin)
    assert len(volume._add_tet_block.signatures) == 1
    np.testing.assert_allclose(data, twin, rtol=1e-12, atol=1e-12 * np.abs(twin).max())


# ------------------------------------------------------------- the gravity release's volume range

#: the flat tet's apex mass [kg], base area [m^2] (equilateral, circumradius 20 mm)
APEX_MASS, BASE_AREA = 1e-3, 0.75 * np.sqrt(3.0) * 0.02 ** 2
#: its volume stiffness [Pa] for a static sag to V/V0 = 0.6 under GRAVITY (the volume term
#: carrying the apex: kv A/3 (1 - J) = m g)
SAG_KV = 3.0 * APEX_MASS * 9.81 / (0.4 * BASE_AREA)


def flat_tet(kv=SAG_KV, K0=1.0, free=(False, False, False, True), arms=None):
    """A flat tet (sliver): an equilateral base of circumradius R = 20 mm in z = 0 under an
    apex at height h = R/4 above its centre, the apex 1 g, the base vertices 10 g; linear
    springs K0 [N/m] on the edges (arms of negligible stiffness), kv [Pa] on the tet (with
    ``arms`` (kv1, kv2) [Pa], relaxation times 0.05 / 0.5 s), ``free`` the vertices that move.
    Lowering the apex by d shrinks V/V0 to 1 - d/h while its edges shorten by only about
    h d/(R^2 + h^2): the volume falls 18x faster than a uniform compression of the edges."""
    R, h = 0.02, 0.005
    angles = 2 * np.pi * np.arange(3) / 3
    x = np.vstack([np.column_stack([R * np.cos(angles), R * np.sin(angles), np.zeros(3)]),
                   [[0.0, 0.0, h]]])
    builder = ModelBuilder()
    builder.add_particles(x, np.array([1e-2, 1e-2, 1e-2, APEX_MASS]), ~np.array(free))
    builder.add_connectors([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
    params = dataclasses.replace(viscoelastic_params(6, K0, **ELASTIC), kv=np.array([kv]))
    model = builder.finalize(params, tets=np.array([[0, 1, 2, 3]]))
    return model if arms is None else with_kv(model, kv, arms)


def apex_lowered(model, ratio):
    """(4, 3) displacement [m] lowering the flat tet's apex to V/V0 = ``ratio``."""
    u = np.zeros((4, 3))
    u[3, 2] = -(1.0 - ratio) * model.rest_positions[3, 2]
    return u


def volume_ratio(model, displacement):
    """V/V0 of the (one) tet at ``displacement`` (..., N, 3) [m]."""
    x = model.rest_positions + np.asarray(displacement)
    return np.array([signed_volumes(y, model.tets)[0] for y in x.reshape(-1, *x.shape[-2:])]
                    ).reshape(x.shape[:-2]) / model.rest_volumes[0]


def test_the_release_volume_range_is_the_connectors_rule_on_each_tets_volume_strain():
    """release_volume_range on the flat tet: the apex lowered to V/V0 = J_s with the edges
    barely shorter, so the cube of the connectors' release range misses the tet's own
    static volume. The range is that one widened to 1 + [min(0, 2 j_s) - m, max(0, 2 j_s) +
    m] (j_s = J_s - 1): twice the static volume strain with the margin (J_s = 0.8, m = 0.05:
    0.55; J_s = 0.6: 0.15), cut at 0 (J_s = 0.3, and a statically inverted tet, J_s = -0.2),
    the upper end kept where the cube range is wider. A tet whose static overshoot is inside
    the cube range keeps it bit for bit; no range without the volume term."""
    model = flat_tet()
    for ratio, expected in ((0.8, 0.55), (0.6, 0.15), (0.3, 0.0), (-0.2, 0.0)):
        static = apex_lowered(model, ratio)
        strains = strain_range_for_release(model, static, 0.05)
        cube_lo, cube_hi = volume_ratio_range(model, *strains)
        j_lo, j_hi = release_volume_range(model, static, 0.05, strains)
        assert cube_lo[0] > ratio  # the edges shorten by at most 4 %: the cube misses J_s
        assert j_lo[0] == pytest.approx(expected, abs=1e-12)
        assert j_hi[0] == cube_hi[0]  # (1 + m)^3 > 1 + m: the cube's upper end is wider
    # the apex raised to V/V0 = 1.02: 1 + 2 x 0.02 + 0.05 is inside the cube's upper end
    static = apex_lowered(model, 1.02)
    strains = strain_range_for_release(model, static, 0.05)
    cube = volume_ratio_range(model, *strains)
    own = release_volume_range(model, static, 0.05, strains)
    assert np.array_equal(own[0], cube[0]) and np.array_equal(own[1], cube[1])
    springs = model.with_params(dataclasses.replace(model.params, kv=None))
    assert release_volume_range(springs, static, 0.05, strains) is None


def test_a_sliver_squeezed_beyond_its_edges_range_is_verified_and_its_release_runs():
    """The flat tet's apex sagging under gravity (springs 1 N/m, kv for a sag to V/V0 = 0.6:
    the volume term carries the weight, up to the springs' share of a few %). Released from
    rest, the undamped elastic apex swings to twice its static volume strain, V/V0 = 0.2,
    far below the cube of its connectors' release range (0.76 with the margin 0.05). The
    gravity test (static sag, then the release at the step chosen for its ranges) completes
    and reaches V/V0 = 2 J_s - 1 (2e-2: the springs' share and the sampling at 0.5 ms),
    inside the range it verified (from 0.15); the same run on the cube range alone stops at
    its lower end, naming the tet."""
    from forcecal.scene import ParticleSection
    from particle.experiments import gravity_dynamic, gravity_test
    model = flat_tet()
    particle = ParticleSection(strain_margin=0.05)
    times = np.linspace(0.0, 0.3, 601)  # about three periods of the apex (0.09 s)
    test = gravity_test(model, GRAVITY, times, load_steps=2, particle=particle,
                        strain_range=(-0.5, 0.5), name="flat tet")
    static = volume_ratio(model, test.static_displacement)
    assert static == pytest.approx(0.6, abs=0.02)
    strains, volumes = release_ranges(model, test.static_displacement, particle, (-0.5, 0.5))
    cube = volume_ratio_range(model, *strains)[0][0]
    ratios = volume_ratio(model, test.displacement)
    assert ratios.min() == pytest.approx(2.0 * static - 1.0, abs=0.02)
    assert volumes[0][0] < ratios.min() and cube > 0.75
    with pytest.raises(StabilityError, match=rf"tet 0 \(particles 0-1-2-3\) reached volume ratio "
                       rf"V/V0 = 0\.7\d+ at step \d+ .* outside \[{cube:.4g}, "):
        gravity_dynamic(model, GRAVITY, times[-1], test.dt, times, strain_range=strains)


def test_a_tet_leaving_its_release_volume_range_still_stops_the_run_naming_it():
    """The flat tet released on the volume range of half its static sag without margin (V/V0
    down to 1 + 2 (0.8 - 1) = 0.6, below the cube range of its strains): the apex swings to
    0.2, so the run stops with StabilityError naming the tet, its volume ratio and the
    range, never NaN."""
    from particle.experiments import gravity_dynamic
    model = flat_tet()
    static = gravity_static(model, GRAVITY)
    strains = strain_range_for_release(model, static, 0.05)
    volumes = release_volume_range(model, 0.5 * static, 0.0, strains)
    assert volumes[0][0] == pytest.approx(2.0 * volume_ratio(model, 0.5 * static) - 1.0,
                                          rel=1e-12)
    assert volumes[0][0] < volume_ratio_range(model, *strains)[0][0]
    times = np.linspace(0.0, 0.1, 201)
    dt = 0.9 * critical_time_step(model, strain_range=strains, volume_range=volumes)
    with pytest.raises(StabilityError, match=r"tet 0 \(particles 0-1-2-3\) reached volume ratio "
                       r"V/V0 = 0\.\d+ at step \d+ .* outside \[0\.6\d*, \d\.\d+\], the "
                       r"range the step was verified stable for") as stop:
        gravity_dynamic(model, GRAVITY, times[-1], dt, times, strain_range=strains,
                        volume_range=volumes)
    reached = float(re.search(r"V/V0 = ([\d.]+)", str(stop.value)).group(1))
    assert reached < volumes[0][0]


@pytest.mark.parametrize("arms", [None, (150.0, 100.0)], ids=["elastic", "viscoelastic"])
def test_the_step_bound_holds_at_sampled_states_of_a_volume_range_below_the_cube_one(arms):
    """Rigour on a given volume range: the flat tet with every vertex free (its curvature
    blocks d^2V/dp_a dp_b all present), strains in +-0.1 (the cube range [0.729, 1.331]) and
    the release range of a static sag to V/V0 = 0.6 without margin ([0.2, 1.331]). At the
    apex lowered to V/V0 in 0.21 .. 1 (below the cube range from 0.7 on) plus random
    perturbations of every vertex (0.2 mm), those inside both ranges, the largest
    mass-scaled eigenvalue of the exact tangent (linear springs: K0 e e^T + F/l (I - e e^T)
    per connector; the volume term's numpy Hessian, with the arms at their largest step
    coefficient kv1 + kv2 and a summed pressure of +- their bound (kv1 + kv2)(J_hi - J_lo))
    is at most the step bound of these ranges, which is above the cube range's."""
    K0 = 20.0
    model = flat_tet(kv=2000.0, K0=K0, free=(True,) * 4, arms=arms)
    lo, hi = np.full(6, -0.1), np.full(6, 0.1)
    volumes = release_volume_range(model, apex_lowered(model, 0.6), 0.0, (lo, hi))
    assert volumes[0][0] == pytest.approx(0.2, rel=1e-12)
    assert volumes[1][0] == pytest.approx(1.1 ** 3, rel=1e-12)
    omega2 = step_bound(model, (lo, hi), volume_range=volumes).omega2
    assert omega2 > step_bound(model, (lo, hi)).omega2
    rng = np.random.default_rng(3)
    scale = np.repeat(1.0 / np.sqrt(model.masses), 3)
    largest, below_cube = 0.0, 0
    for ratio in np.linspace(0.21, 1.0, 9):
        for k in range(4):
            x = model.rest_positions + apex_lowered(model, ratio)
            x += (0.0 if k == 0 else 2e-4) * rng.standard_normal(x.shape)
            d = x[model.edges[:, 1]] - x[model.edges[:, 0]]
            length = np.linalg.norm(d, axis=1)
            strain = length / model.rest_lengths - 1.0
            j = signed_volumes(x, model.tets)[0] / model.rest_volumes[0]
            if not (np.all((lo <= strain) & (strain <= hi))
                    and volumes[0][0] < j <= volumes[1][0]):
                continue
            below_cube += j < 0.9 ** 3
            tangent = np.zeros((12, 12))
            for (a, b), e, l, l0 in zip(model.edges, d, length, model.rest_lengths):
                n = np.outer(e, e) / l ** 2
                block = K0 * n + K0 * (l - l0) / l * (np.eye(3) - n)
                for p, q, sign in ((a, a, 1), (b, b, 1), (a, b, -1), (b, a, -1)):
                    tangent[3 * p:3 * p + 3, 3 * q:3 * q + 3] += sign * block
            for sign in ((None,) if arms is None else (-1.0, 1.0)):
                extra = () if arms is None else (
                    sum(arms), sign * sum(arms) * (volumes[1][0] - volumes[0][0]))
                full = tangent + volume_hessian_numpy(x, model.tets[0], model.rest_volumes[0],
                                                      model.params.kv[0], *extra)
                top = float(np.linalg.eigvalsh(scale[:, None] * full * scale[None, :]).max())
                largest = max(largest, top)
                assert top <= omega2
    assert below_cube >= 8 and largest > 0.0


@VOLUME_TERMS
def test_a_release_whose_static_volumes_are_inside_the_cube_range_is_unchanged(arms):
    """A box with the volume term sagging under gravity (every tet's static overshoot inside
    the cube of its connectors' release range, margin 0.2): the release's volume range is
    that cube range bit for bit, so are its stable step and its displacements (the run as
    it was without a range of the tets' own)."""
    from forcecal.scene import ParticleSection
    from particle.experiments import gravity_dynamic
    model = with_kv(box_model((3, 3, 2), K0=10.0, a=-4.0, b=60.0), 3000.0, arms)
    static = gravity_static(model, GRAVITY)
    strains, volumes = release_ranges(model, static, ParticleSection(), (-0.5, 0.5))
    cube = volume_ratio_range(model, *strains)
    assert np.array_equal(volumes[0], cube[0]) and np.array_equal(volumes[1], cube[1])
    assert np.abs(volume_ratio(model, static) - 1.0).max() > 0.01  # the sag changes volumes
    dt = critical_time_step(model, strain_range=strains)
    assert critical_time_step(model, strain_range=strains, volume_range=volumes) == dt
    times = np.linspace(0.0, 0.05, 11)
    before = gravity_dynamic(model, GRAVITY, times[-1], 0.9 * dt, times, strain_range=strains)
    after = gravity_dynamic(model, GRAVITY, times[-1], 0.9 * dt, times, strain_range=strains,
                            volume_range=volumes)
    assert np.array_equal(before, after) and np.abs(after).max() > 0.0


def test_a_given_volume_ratio_range_is_checked_naming_the_tet():
    """verified_ratio_range refuses a range it could not verify or bound: the wrong shape, a
    lower end below 0 or above 1 (the rest state), an upper end below 1, non-finite ends;
    ParameterError naming the tet. The runs and the stable step check it the same way."""
    from particle.volume_bounds import verified_ratio_range
    model = with_kv(box_model((2, 2, 2)), 1000.0)
    n = model.n_tets
    lo, hi = np.full(model.n_connectors, -0.1), np.full(model.n_connectors, 0.1)
    with pytest.raises(ParameterError, match=r"expected one per tet \(%d,\)" % n):
        verified_ratio_range(model, lo, hi, (np.zeros(3), np.ones(3)))
    for j_lo, j_hi in ((-0.1, 2.0), (1.1, 2.0), (0.5, 0.9), (np.nan, 2.0), (0.5, np.inf)):
        bad = (np.full(n, 0.5), np.full(n, 2.0))
        bad[0][4], bad[1][4] = j_lo, j_hi
        with pytest.raises(ParameterError, match=r"tet 4 \(particles [0-9-]+\): volume ratio "
                           r"range .* must be finite with 0 <= lo <= 1 <= hi"):
            verified_ratio_range(model, lo, hi, bad)
        with pytest.raises(ParameterError, match=r"tet 4 "):
            VerletIntegrator(strain_range=(lo, hi), volume_range=bad).prepare(model, 1e-5)
    good = (np.full(n, 0.5), np.full(n, 2.0))
    checked = verified_ratio_range(model, lo, hi, good)
    assert np.array_equal(checked[0], good[0]) and np.array_equal(checked[1], good[1])
