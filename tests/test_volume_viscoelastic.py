"""The viscoelastic volume term (particle/volume.py with Maxwell arms): closed-form Maxwell
responses, twins, tangent, energy, stability bound, statics, haptics, refusals."""
import dataclasses

import numpy as np
import pytest

from forcecal.errors import ConvergenceError, ParameterError
from forcecal.scene import load_scene, replace
from particle.evaluators import IndentationEvaluator, RelaxationEvaluator
from particle.guard import energy_bound
from particle.integrator import VerletIntegrator
from particle.model import ModelBuilder, Prescribed
from particle.params import maxwell_recursions, viscoelastic_params
from particle.stability import critical_time_step
from particle.statics import (ArmStep, EquilibriumSolver, TangentPattern, VolumeArmStep,
                              gravity_static)
from tests.particle_models import box_model, spring_energy, top_centre, volume_pass
from particle.volume import (add_volume_tangent, add_volume_tangent_numpy,
                             signed_volumes, volume_arm_energy, volume_arm_pressures_numpy,
                             volume_energy, volume_forces_numpy, volume_gradients_numpy,
                             volume_strains)
from tests.test_particle_volume import (ELASTIC, GRAVITY, TET, central_gradient, deformed,
                                       random_tets, tangent_and_differences, with_kv)
from tests.conftest import SCENES

KV, ARMS, TAU = 1000.0, (600.0, 400.0), (0.05, 0.5)


def with_volume(model, kv=KV, arms=ARMS, tau=TAU):
    """The model with kv [Pa] and volume arms of stiffnesses ``arms`` [Pa] and times ``tau``
    [s] on every tet."""
    return with_kv(model, kv, arms, tau)


def single_tet(K0=1e-9):
    """One tet, vertices 0-2 fixed, 3 free; springs and their arms negligible."""
    builder = ModelBuilder()
    builder.add_particles(TET, np.full(4, 1e-3), np.array([True, True, True, False]))
    builder.add_connectors([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
    model = builder.finalize(viscoelastic_params(6, K0, **ELASTIC), tets=np.array([[0, 1, 2, 3]]))
    return with_volume(model)


def maxwell_solid(times, rate, ramp_time, kv=KV, arms=ARMS, tau=TAU):
    """Closed-form pressure [Pa] of a Maxwell-Solid (spring kv, arms kv_i, tau_i) under the
    volume strain ramp ``j = rate t`` up to ``ramp_time``, then held."""
    t = np.asarray(times)
    j = rate * np.minimum(t, ramp_time)
    p = kv * j
    for k, tt in zip(arms, tau):
        at_end = k * tt * rate * (1.0 - np.exp(-ramp_time / tt))
        p = p + np.where(t <= ramp_time, k * tt * rate * (1.0 - np.exp(-t / tt)),
                         at_end * np.exp(-(t - ramp_time) / tt))
    return p


def pushed_vertex(model):
    """(inward unit normal of the free vertex's push, area of its opposite face / 3 [m^2]):
    moving vertex 3 along the normal of face 0-1-2 changes V linearly (V is affine in each
    vertex), ``dV = -area/3 d`` for a push by d."""
    g = volume_gradients_numpy(model.rest_positions, model.tets)[0, 3]
    return -g / np.linalg.norm(g), float(np.linalg.norm(g))


RAMP, HOLD = 0.1, 1.5
SAMPLES = np.r_[np.linspace(0.01, RAMP, 10), RAMP + np.geomspace(0.01, HOLD, 20)]


def test_quasi_static_ramp_and_hold_is_the_closed_form_maxwell_solid():
    """Vertex 3 pushed towards its opposite face at a constant rate, then held: the volume
    strain is an exact ramp, and the relaxation path (exact recursion, linear strain within
    each step) reproduces the continuous Maxwell-Solid's pressure, times area/3, to round-off
    (the negligible springs, 1e-9 N/m, give 1e-10 of it)."""
    model = single_tet()
    normal, area3 = pushed_vertex(model)
    depth = 1e-3
    depths = depth * np.minimum(SAMPLES / RAMP, 1.0)
    relax = RelaxationEvaluator(model, [3], normal[None], SAMPLES, depths)
    force = relax(model.params)[0]
    rate = -area3 * depth / RAMP / model.rest_volumes[0]  # dj/dt of the ramp
    expect = -maxwell_solid(SAMPLES, rate, RAMP) * area3
    np.testing.assert_allclose(force, expect, rtol=1e-9)
    # the arms relax: at the end only kv holds the load (the long-term indentation force)
    static = IndentationEvaluator(model, [3], normal[None], [depth])(model.params)[0, 0]
    assert static == pytest.approx(-KV * rate * RAMP * area3, rel=1e-9)
    assert force[9] > 1.5 * static  # at the ramp's end the arms carry 55 % more


def test_explicit_ramp_and_hold_follows_the_maxwell_solid_to_first_order_in_dt():
    """The same test with the explicit run (prescribed vertex, the paper's backward-Euler
    recursion at dt = 1e-5 s, the force sampled at the steps nearest the sample times):
    within 2e-5 of the closed form's largest force (measured 8.0e-6: the recursion's error
    is O(dt/tau1)), and the error doubles with dt (first order: measured 2.00)."""
    model = single_tet()
    normal, area3 = pushed_vertex(model)
    depth = 1e-3
    x3 = model.rest_positions[3]
    motion = Prescribed([3], [0.0, RAMP, RAMP + HOLD],
                        [[x3], [x3 + depth * normal], [x3 + depth * normal]])
    rate = -area3 * depth / RAMP / model.rest_volumes[0]
    errors = []
    for dt in (1e-5, 2e-5):
        run = VerletIntegrator().prepare(model, dt, prescribed_nodes=[3])
        state = model.state()
        forces, times = [], []
        for t in SAMPLES:
            n = int(round((t - state.t) / dt))
            f = run(state, n, (motion.times, motion.positions),
                    energy_bound(model, state, dt, n, None, motion), probe=3)
            forces.append(-f @ normal)
            times.append(state.t)
        expect = -maxwell_solid(np.array(times), rate, RAMP) * area3
        errors.append(np.abs(np.array(forces) - expect).max() / np.abs(expect).max())
    assert errors[0] < 2e-5
    assert errors[1] / errors[0] == pytest.approx(2.0, rel=0.05)


def volume_case(rng, n_tets=24):
    """Random disjoint tets (deformed, compressed, inverted, stretched) with random volume
    arms, an arm state and arm coefficients; the kernels' arm tuple with scratch outputs."""
    model, x = random_tets(n_tets, rng)
    kv = model.params.kv
    model = model.with_params(dataclasses.replace(
        model.params, kv1=0.6 * kv, bv1=0.03 * kv, kv2=0.4 * kv, bv2=0.2 * kv))
    r, c = model.params.volume_arm_recursion(1e-3)
    prev = rng.normal(0.0, 50.0, (n_tets, 2))
    strain_prev = rng.normal(0.0, 0.05, n_tets)
    return model, x, (r, c, prev, strain_prev)


def test_compiled_volume_forces_with_arms_equal_the_numpy_twin():
    """add_volume_forces with arms (scratch outputs: the arm state untouched) against
    volume_forces_numpy with volume_arm_pressures_numpy: forces, new pressures and strains
    to 1e-12 (round-off of two volume formulas; measured 1e-15)."""
    rng = np.random.default_rng(3)
    model, x, (r, c, prev, strain_prev) = volume_case(rng)
    kept = prev.copy(), strain_prev.copy()
    out_p, out_j = np.empty_like(prev), np.empty_like(strain_prev)
    forces = np.zeros_like(x)
    volume_pass(x, model.tets, model.rest_volumes, model.params.kv, forces,
                (r, c, prev, strain_prev, out_p, out_j))
    np.testing.assert_array_equal(prev, kept[0])
    np.testing.assert_array_equal(strain_prev, kept[1])
    strain = volume_strains(x, model.tets, model.rest_volumes)
    pressure = volume_arm_pressures_numpy(strain, r, c, prev, strain_prev)
    twin = volume_forces_numpy(x, model.tets, model.rest_volumes, model.params.kv,
                               pressure.sum(axis=1))
    scale = np.abs(twin).max()
    np.testing.assert_allclose(forces, twin, rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(out_p, pressure, rtol=0, atol=1e-12 * np.abs(pressure).max())
    np.testing.assert_allclose(out_j, strain, rtol=0, atol=1e-12)
    # the arms really act: without them the forces differ
    elastic = volume_forces_numpy(x, model.tets, model.rest_volumes, model.params.kv)
    assert np.abs(elastic - twin).max() > 0.1 * scale


def test_tangent_kernel_with_arms_equals_its_numpy_twin_and_the_force_derivative():
    """add_volume_tangent with an arm step's coefficients and pressures against its numpy twin
    (round-off) and against central differences of the statics' forces in that arm step
    (springs + volume + both arms; O(h^2) ~ 1e-8)."""
    rng = np.random.default_rng(4)
    model, x, (r, c, prev, strain_prev) = volume_case(rng)
    slots = TangentPattern.of(model).tet_slots
    nnz = int(slots.max()) + 1
    strain = volume_strains(x, model.tets, model.rest_volumes)
    arms = (c.sum(axis=1), volume_arm_pressures_numpy(strain, r, c, prev,
                                                      strain_prev).sum(axis=1))
    compiled, twin = np.zeros(nnz), np.zeros(nnz)
    args = (x, model.tets, model.rest_volumes, model.params.kv, slots)
    add_volume_tangent(*args, compiled, arms)
    add_volume_tangent_numpy(*args, twin, arms)
    np.testing.assert_allclose(compiled, twin, rtol=0, atol=1e-12 * np.abs(twin).max())
    # the assembled tangent of a relaxation step on the box against the forces' derivative
    box = with_volume(box_model((2, 2, 2), a=-20.0, b=300.0), 4000.0, (2000.0, 1500.0))
    p = box.params
    e, t = box.n_connectors, box.n_tets
    rc = p.arm_recursion(0.02, exact=True)
    vrc = p.volume_arm_recursion(0.02, exact=True)
    step = ArmStep(*rc, rng.normal(0, 0.01, (e, 2)), rng.normal(0, 1e-4, e),
                   VolumeArmStep(*vrc, rng.normal(0, 20.0, (t, 2)), rng.normal(0, 0.01, t)))
    tangent, fd = tangent_and_differences(box, deformed(box, 5e-4, seed=3), step)
    np.testing.assert_allclose(tangent, fd, rtol=0, atol=1e-6 * np.abs(fd).max())


def test_the_forces_of_an_arm_step_are_minus_the_gradient_of_its_incremental_potential():
    """Within one arm step the volume forces derive from ``W = sum V0 [kv/2 j^2 + sum_i ((r_i
    P_i^prev - c_i j^prev) j + c_i/2 j^2)]`` (its gradient is ``(kv j + sum_i P_i) dV/dx``):
    central differences of W against the compiled forces (O(h^2) ~ 1e-7)."""
    rng = np.random.default_rng(5)
    model, _, (r, c, prev, strain_prev) = volume_case(rng, 8)
    x = deformed(model, 1e-3, seed=6)
    kv, v0 = model.params.kv, model.rest_volumes

    def potential(y):
        j = volume_strains(y, model.tets, v0)
        lin = (r * prev - c * strain_prev[:, None]).sum(axis=1)
        return float(np.sum(v0 * (0.5 * kv * j * j + lin * j + 0.5 * c.sum(axis=1) * j * j)))

    forces = np.zeros_like(x)
    volume_pass(x, model.tets, v0, kv, forces,
                (r, c, prev, strain_prev, np.empty_like(prev), np.empty_like(strain_prev)))
    fd = -central_gradient(potential, x)
    np.testing.assert_allclose(forces, fd, rtol=0, atol=1e-6 * np.abs(fd).max())


def test_a_released_tet_loses_energy_only_to_its_dashpots():
    """The free vertex pushed 1 mm towards its opposite face and released (springs + relaxing
    volume term): the stored energy (kinetic + springs + volume + the volume arms' springs)
    never rises above its start beyond position Verlet's bounded error (1 % at dt = 0.1 x
    the limit, as the elastic test; measured 0.5 %), and the dashpots take more than half
    of it within 20 tau1 (measured 60 %)."""
    model = single_tet(K0=20.0)
    dt = 0.1 * critical_time_step(model)
    state = model.state()
    state.x[3] += 1e-3 * pushed_vertex(model)[0]
    state.x_prev[:] = state.x
    p = model.params

    def energy(s):
        v = (s.x - s.x_prev) / dt
        pot = np.mean([spring_energy(model, y) + volume_energy(y, model.tets, model.rest_volumes,
                                                               p.kv) for y in (s.x, s.x_prev)])
        arms = volume_arm_energy(s.volume_arm, p.volume_arm_stiffness, model.rest_volumes)
        return 0.5 * float(np.sum(model.masses[:, None] * v ** 2)) + pot + arms

    integrator = VerletIntegrator()
    integrator.simulate(model, state, dt, 1)
    e0 = energy(state)
    values = []
    steps = int(20 * TAU[0] / dt / 200) + 1
    for _ in range(200):
        integrator.simulate(model, state, dt, steps)
        values.append(energy(state))
    assert max(values) < (1 + 1e-2) * e0
    assert values[-1] < 0.5 * e0


def test_the_long_term_statics_are_the_elastic_terms():
    """Static sag and indentation curves see kv alone (the arms relaxed): bit for bit the
    elastic term's; a relaxation curve starts above the elastic term's (measured +4.4 % at
    5 ms: the box's springs carry most of the force) and ends on the static force."""
    model = with_volume(box_model((3, 3, 2), density=1000.0), 4000.0, (2400.0, 1600.0))
    elastic = model.with_params(dataclasses.replace(model.params, kv1=None, bv1=None, kv2=None,
                                                    bv2=None))
    np.testing.assert_array_equal(gravity_static(model, GRAVITY), gravity_static(elastic, GRAVITY))
    node = top_centre(model)
    normal = np.array([[0.0, 0.0, -1.0]])
    depth = 1e-3
    static = IndentationEvaluator(model, [node], normal, [depth])
    assert static(model.params)[0, 0] == static(elastic.params)[0, 0]
    relax = RelaxationEvaluator(model, [node], normal, [0.005, 1.0, 5.0, 10.0], [depth] * 4)
    with_arms, without = relax(model.params)[0], relax(elastic.params)[0]
    assert with_arms[0] > 1.03 * without[0]  # the volume arms stiffen the early response
    assert with_arms[-1] == pytest.approx(static(model.params)[0, 0], rel=2e-5)


def test_one_volume_arm_value_for_every_tet_is_broadcast_like_kv():
    """Parameters with one kv and one value per volume arm ((1,), a global fit's) give bit for
    bit the curves and the explicit run of the same values on every tet: the arms' recursion
    is taken from the model's broadcast parameters (the kernels index them per tet)."""
    model = with_volume(box_model())
    p = model.params
    one = dataclasses.replace(p, **{n: getattr(p, n)[:1] for n in ("kv", "kv1", "bv1", "kv2",
                                                                     "bv2")})
    node = top_centre(model)
    relax = RelaxationEvaluator(model, [node], np.array([[0.0, 0.0, -1.0]]),
                                [0.01, 0.1, 1.0], [5e-4] * 3)
    np.testing.assert_array_equal(relax(one), relax(p))
    states = []
    for params in (one, p):
        m = model.with_params(params)
        state = m.state()
        VerletIntegrator().simulate(m, state, 0.5 * critical_time_step(m), 100, gravity=GRAVITY)
        states.append(state)
    np.testing.assert_array_equal(states[0].x, states[1].x)
    np.testing.assert_array_equal(states[0].volume_arm, states[1].volume_arm)


def test_the_volume_arm_recursion_is_the_connectors_one():
    """kv_i, bv_i through the one Maxwell recursion: both forms, bit for bit."""
    model = with_volume(box_model())
    p = model.params
    for exact in (False, True):
        r, c = p.volume_arm_recursion(2e-3, exact=exact)
        rr, cc = maxwell_recursions(p.volume_arm_stiffness, p.volume_arm_tau, np.array([2e-3]),
                                    exact=exact)
        np.testing.assert_array_equal(r, rr[0])
        np.testing.assert_array_equal(c, cc[0])
    assert np.allclose(p.volume_arm_tau, TAU)


def test_bad_volume_arms_and_states_are_refused_by_name():
    model = with_volume(box_model())
    for name in ("kv1", "bv2"):
        bad = getattr(model.params, name).copy()
        bad[5] = -1.0
        with pytest.raises(ParameterError, match=rf"tet 5 \(particles [0-9-]+\): volume arm "
                                                 rf"{name} = -1.0 Pa"):
            VerletIntegrator().prepare(model.with_params(dataclasses.replace(
                model.params, **{name: bad})), 1e-5)
    with pytest.raises(ParameterError, match="the volume term's arms need kv and all of"):
        dataclasses.replace(model.params, kv2=None)
    with pytest.raises(ParameterError, match="the volume term's arms need kv"):
        dataclasses.replace(model.params, kv=None)
    with pytest.raises(ParameterError, match=r"kv1 of shape \(3,\) does not match kv's"):
        dataclasses.replace(model.params, kv1=np.ones(3))
    state = model.state()
    state.volume_arm = None
    with pytest.raises(ParameterError, match="the state has no volume_arm"):
        VerletIntegrator().simulate(model, state, 1e-5, 1)
    state = model.state()
    state.volume_prev[3] = np.nan
    with pytest.raises(ParameterError, match=r"state.volume_prev has non-finite values at tet 3"):
        VerletIntegrator().simulate(model, state, 1e-5, 1)


def test_the_scene_key_takes_viscoelastic_and_keeps_true_and_false():
    scene = load_scene(SCENES / "tiny.toml")
    for value, arms in ((True, False), (False, False), ("viscoelastic", True)):
        particle = replace(scene, particle={"volume": value}).particle
        assert particle.volume == value and particle.volume_arms == arms
    with pytest.raises(Exception, match="particle.volume = 'elastic': must be one of"):
        replace(scene, particle={"volume": "elastic"})


def test_an_inverted_guess_is_never_returned_as_an_equilibrium():
    """A tet inverted at the guess makes every force infinite (no admissible iterate): the
    indenter's reaction, hence the force scale of the convergence test, is infinite too,
    which must not pass for convergence (inf <= rtol x inf). Here no particle is free, so
    Newton cannot move the guess: ConvergenceError, never infinite reaction forces."""
    model = single_tet(K0=1.0)
    x = model.rest_positions.copy()
    x[3, 2] = -x[3, 2]  # through its opposite face (z = 0)
    assert signed_volumes(x, model.tets)[0] < 0
    solver = EquilibriumSolver(model, np.array([3]), TangentPattern.of(model))
    with pytest.raises(ConvergenceError, match="Newton did not converge"):
        solver.solve(x, model.params)
