"""Explicit dynamics: conservation, compiled vs numpy step, term skipping, stability limit."""
import dataclasses

import numpy as np
import pytest
import scipy.linalg

from forcecal.errors import ParameterError, StabilityError
from forcecal.scene import ParticleSection
from particle import kernels
from particle.haptics import HapticSession
from particle.integrator import VerletIntegrator
from particle.stability import critical_time_step, resolve_time_step
from particle.model import Model, Prescribed, State
from particle.reference_numpy import step_numpy
from tests.particle_models import box_model, deformed_start_and_push, mechanical_energy, top_centre

GRAVITY = np.array([0.0, 0.0, -9.81])


def _perturbed(model: Model, dt: float, amplitude: float, seed: int = 1) -> State:
    """A running state: random displacements and velocities of the free particles."""
    rng = np.random.default_rng(seed)
    state = model.state()
    free = model.free_nodes
    size = np.ptp(model.rest_positions)
    state.x[free] += amplitude * size * rng.standard_normal((len(free), 3))
    velocity = amplitude * size / (200 * dt) * rng.standard_normal((len(free), 3))
    state.x_prev[free] = state.x[free] - velocity * dt
    state.dt = dt
    d = state.x[model.edges[:, 1]] - state.x[model.edges[:, 0]]
    state.dx_prev[:] = np.linalg.norm(d, axis=1) - model.rest_lengths  # arms relaxed here
    return state


def _energy(model: Model, state: State) -> float:
    """Kinetic + elastic energy [J] of a linear spring network without arms.

    The velocity at the current step is v^{n-1/2} + dt/2 a^n (second order), not the
    lagging backward difference.
    """
    p = model.params
    forces, dx = np.empty_like(state.x), np.empty(model.n_connectors)
    kernels.internal_forces(state.x, model.edges, model.rest_lengths, p.K0, None, None, None,
                            None, None, None, forces, np.empty(model.n_connectors), None, dx)
    m = model.masses[:, None]
    v = (state.x - state.x_prev) / state.dt + 0.5 * state.dt * forces / m
    return 0.5 * float(np.sum(m * v ** 2)) + 0.5 * float(np.sum(p.K0 * dx ** 2))


def test_free_body_conserves_momentum_and_keeps_energy_bounded_over_1e5_steps():
    """A free box (27 particles) with nonlinear springs and arms, and the same box linear and
    elastic, each run undamped for 1e5 steps (omega dt <= 0.4)."""
    model = box_model((2, 2, 2), fixed_bottom=False, a=-20.0, b=300.0)
    dt = 0.2 * critical_time_step(model)
    integrator = VerletIntegrator()
    n, chunks = 100_000, 100
    # momentum: internal forces (springs and arms) cancel pairwise, so sum m (x^{n+1} - x^n)/dt
    # is constant up to round-off. Each step rounds the positions (relative eps), so n steps
    # can move it by at most n M eps |x|_max / dt.
    state = _perturbed(model, dt, 0.01)
    momentum0 = model.masses @ (state.x - state.x_prev) / dt
    # energy with arms: kinetic + spring + arm-spring energy (mechanical_energy). The dashpots
    # only dissipate (and the backward-Euler arm step is dissipative too), so the energy can
    # only rise by Verlet's bounded oscillation, (omega dt)^2/8 <= 0.02 of it: every sample
    # stays below the lowest one before it + 2 % of the start, and the arms take energy out
    # (measured: no rise above 2e-11 of the start, 0.3 % of it left at the end)
    energies = [mechanical_energy(model, state, np.zeros(3))[0]]
    for _ in range(chunks):
        integrator.simulate(model, state, dt, n // chunks)
        energies.append(mechanical_energy(model, state, np.zeros(3))[0])
    momentum = model.masses @ (state.x - state.x_prev) / dt
    roundoff = n * model.masses.sum() * np.finfo(float).eps * np.abs(state.x).max() / dt
    np.testing.assert_allclose(momentum, momentum0, rtol=0, atol=roundoff)
    assert np.abs(momentum0).max() > 1e3 * roundoff  # the check is not vacuous
    energies = np.array(energies)
    rise = energies - np.minimum.accumulate(energies)
    assert rise.max() < 0.02 * energies[0]
    assert energies[-1] < 0.1 * energies[0]
    # linear elastic: Verlet is symplectic, so the energy oscillates by about
    # (omega dt)^2/8 <= 0.02 (7e-4 measured) and does not drift (2e-5 measured between the
    # first and last 20 % of the run)
    linear = model.with_params(dataclasses.replace(model.params, a=0 * model.params.a,
                                                   b=0 * model.params.b))
    state = _perturbed(linear, dt, 0.01)
    energies = [_energy(linear, state)]
    for _ in range(chunks):
        integrator.simulate(linear, state, dt, n // chunks, arms=False)
        energies.append(_energy(linear, state))
    energies = np.array(energies)
    assert np.abs(energies / energies[0] - 1.0).max() < 0.02
    assert abs(energies[-20:].mean() / energies[:20].mean() - 1.0) < 1e-3


TERMS = [dict(nonlinear=nl, arms=arms, gravity=g, damping=d, prescribed=p)
         for nl in (False, True) for arms in (False, True) for g in (False, True)
         for d in (False, True) for p in (False, True)]


@pytest.mark.parametrize("terms", TERMS, ids=lambda t: "-".join(k for k, v in t.items() if v)
                         or "linear")
def test_compiled_step_matches_the_numpy_step(terms):
    """Every combination of force terms (each a separate compiled specialisation) and
    prescribed motion, against the plain-numpy step."""
    model = box_model(**(dict(a=-20.0, b=300.0) if terms["nonlinear"] else {}))
    damping = 3.0 if terms["damping"] else 0.0
    gravity = GRAVITY if terms["gravity"] else None
    dt = 0.5 * critical_time_step(model, damping=3.0)
    compiled, push = deformed_start_and_push(model, dt)
    reference = compiled.copy()
    motion = push if terms["prescribed"] else None
    VerletIntegrator(damping).simulate(model, compiled, dt, 50, gravity=gravity,
                                       arms=terms["arms"], prescribed=motion)
    for _ in range(50):
        step_numpy(model, reference, dt, gravity=gravity, damping=damping, arms=terms["arms"],
                   prescribed=motion)
    scale = np.abs(reference.x - model.rest_positions).max()
    # same formulas, same summation order; only x/m vs x*(1/m) and the keyframe time
    # (t0 + n dt vs a sum of dt) differ (an ulp per step)
    np.testing.assert_allclose(compiled.x, reference.x, rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(compiled.arm_force, reference.arm_force, rtol=1e-10,
                               atol=1e-12 * np.abs(reference.arm_force).max())
    np.testing.assert_allclose(compiled.dx_prev, reference.dx_prev, rtol=0, atol=1e-12 * scale)
    assert compiled.t == pytest.approx(reference.t)
    assert compiled.arm_force.any() == terms["arms"]


def test_the_compiled_loop_refuses_its_argument_groups_out_of_order():
    """Two groups swapped (the particles where the connectors go) do not compile: a call in
    the wrong order fails loudly instead of running with K0 read as masses."""
    from numba.core.errors import TypingError

    from particle import step_kernels
    model = box_model()
    run = VerletIntegrator().prepare(model, 0.5 * critical_time_step(model))
    groups = run.arguments(model.state(), 1, run._no_keyframes, 1.0, (None, None, None),
                           run._no_probe)
    swapped = list(groups)
    swapped[1], swapped[3] = groups[3], groups[1]
    with pytest.raises(TypingError):
        step_kernels.run_verlet(*swapped)
    assert step_kernels.run_verlet(*groups).tolist() == [step_kernels.OK, 0, 0]


def test_skipping_terms_gives_identical_results_when_they_are_zero():
    """Compiled-out terms (linear springs, no gravity, no damping, no arms) vs all terms at 0."""
    model = box_model()  # a = b = 0
    dt = 0.5 * critical_time_step(model)
    results = []
    for skip in (True, False):
        state = _perturbed(model, dt, 0.001)
        VerletIntegrator().simulate(model, state, dt, 500, gravity=np.zeros(3), arms=False,
                                    skip=skip)
        results.append(state)
    np.testing.assert_array_equal(results[0].x, results[1].x)
    np.testing.assert_array_equal(results[0].x_prev, results[1].x_prev)
    # gravity and arms on, only the nonlinear spring term skipped
    for skip in (True, False):
        state = _perturbed(model, dt, 0.001)
        VerletIntegrator().simulate(model, state, dt, 500, gravity=GRAVITY, skip=skip)
        results.append(state)
    np.testing.assert_array_equal(results[2].x, results[3].x)
    np.testing.assert_array_equal(results[2].arm_force, results[3].arm_force)


def _exact_critical_step(model: Model) -> float:
    """2/omega_max of the elastic network at rest (dense generalised eigenproblem)."""
    free = model.free_nodes
    dof = np.full(model.n_particles, -1)
    dof[free] = np.arange(len(free))
    n = 3 * len(free)
    K = np.zeros((n, n))
    d = model.rest_positions[model.edges[:, 1]] - model.rest_positions[model.edges[:, 0]]
    e = d / np.linalg.norm(d, axis=1)[:, None]
    for (i, j), unit, k in zip(model.edges, e, model.params.K0):
        block = k * np.outer(unit, unit)
        for a, b, sign in ((i, i, 1), (j, j, 1), (i, j, -1), (j, i, -1)):
            if dof[a] >= 0 and dof[b] >= 0:
                K[3 * dof[a]:3 * dof[a] + 3, 3 * dof[b]:3 * dof[b] + 3] += sign * block
    M = np.repeat(model.masses[free], 3)
    omega2 = scipy.linalg.eigvalsh(K / np.sqrt(np.outer(M, M)))[-1]
    return 2.0 / np.sqrt(omega2)


def test_stability_limit_bounds_the_true_limit_and_divergence_is_caught():
    # arms made negligible so the elastic eigenvalue problem is the whole story
    model = box_model(g=(1e-9, 1e-9))
    exact = _exact_critical_step(model)
    bound = critical_time_step(model)
    assert 0.3 * exact < bound <= exact  # the bound is safe and not absurdly pessimistic
    integrator = VerletIntegrator()
    stable = _perturbed(model, 0.98 * exact, 1e-4)
    integrator.simulate(model, stable, 0.98 * exact, 3000, _check_dt=False)
    assert np.all(np.isfinite(stable.x))
    unstable = _perturbed(model, 1.05 * exact, 1e-4)
    with pytest.raises(StabilityError, match=r"diverged at step \d+ \(t = .* s\): particle \d+"):
        integrator.simulate(model, unstable, 1.05 * exact, 3000, _check_dt=False)


def test_huge_step_raises_instead_of_returning_nan():
    model = box_model()
    dt = 10 * critical_time_step(model)
    state = model.state()
    with pytest.raises(StabilityError, match="diverged"):
        VerletIntegrator().simulate(model, state, dt, 10_000, gravity=GRAVITY, _check_dt=False)


def test_time_step_above_the_limit_is_refused():
    model = box_model()
    critical = critical_time_step(model)
    with pytest.raises(StabilityError, match=r"dt = .* s is above the stability limit"):
        VerletIntegrator().simulate(model, model.state(), 1.01 * critical, 1)
    section = ParticleSection()
    assert resolve_time_step(section, critical) == section.dt_safety * critical
    assert resolve_time_step(ParticleSection(dt=0.9 * critical), critical) == 0.9 * critical
    with pytest.raises(StabilityError, match="above the stability limit"):
        resolve_time_step(ParticleSection(dt=2 * critical), critical)
    # damping lowers the limit: (2/omega)(sqrt(1 + xi^2) - xi)
    assert critical_time_step(model, damping=100.0) < critical


def test_mismatched_inputs_are_refused():
    model = box_model()
    dt = 0.5 * critical_time_step(model)
    other = box_model((2, 2, 2))
    with pytest.raises(ParameterError, match="does not belong to this model"):
        VerletIntegrator().simulate(model, other.state(), dt, 1)
    with pytest.raises(ParameterError, match="n_steps"):
        VerletIntegrator().simulate(model, model.state(), dt, -1)
    with pytest.raises(ParameterError, match="not finite"):
        VerletIntegrator().simulate(model, model.state(), dt, 1, gravity=[0.0, np.nan, 0.0])
    run = VerletIntegrator().prepare(model, dt, prescribed_nodes=[model.free_nodes[0]])
    with pytest.raises(ParameterError, match="do not match the 1 prescribed"):
        run(model.state(), 1, None, 1.0)
    with pytest.raises(ParameterError, match="record_steps"):
        VerletIntegrator().simulate(model, model.state(), dt, 5, record_nodes=[0],
                                    record_steps=[0, 7])


@pytest.mark.parametrize("field, convert, what", [
    ("x", lambda a: a.astype(np.int64), "int64 array"),  # was silently truncated
    ("x_prev", lambda a: a.astype(np.float32), "float32 array"),  # compiled a new kernel
    ("arm_force", np.asfortranarray, "float64 array"),  # (E, 2) in column order
    ("dx_prev", lambda a: a[:-1], r"float64 array of shape \(\d+,\)"),
    ("x", lambda a: a.tolist(), "list"),
])
def test_a_state_of_another_dtype_or_layout_is_refused(field, convert, what):
    model = box_model()
    state = model.state()
    setattr(state, field, convert(getattr(state, field)))
    with pytest.raises(ParameterError, match=rf"the state's {field} \({what}.*\) does not belong "
                       r"to this model .* expected a writeable, C-contiguous float64 array"):
        VerletIntegrator().simulate(model, state, 0.5 * critical_time_step(model), 1)
    state = model.state()
    state.t = np.nan
    with pytest.raises(ParameterError, match="time t = nan s is not finite"):
        VerletIntegrator().simulate(model, state, 0.5 * critical_time_step(model), 1)


@pytest.mark.parametrize("name, value, message", [
    ("K0", -5.0, "K0 = -5 must be > 0"),
    ("k1", 0.0, "k1 = 0 must be > 0"),  # used to run and report a misleading divergence
    ("b1", 0.0, "b1 = 0 must be > 0"),
    ("k2", np.nan, "k2 = nan is not finite"),
])
def test_explicit_runs_refuse_non_physical_parameters(name, value, message):
    """simulate, an unchecked prepare and a haptic session all refuse, naming the connector."""
    model = box_model()
    values = getattr(model.params, name).copy()
    values[7] = value
    bad = model.with_params(dataclasses.replace(model.params, **{name: values}))
    i, j = model.edges[7]
    for run in (lambda: VerletIntegrator().simulate(bad, bad.state(), 1e-5, 10, gravity=GRAVITY),
                lambda: VerletIntegrator().prepare(bad, 1e-5, _check_dt=False),
                lambda: HapticSession(bad, 1e-5)):
        with pytest.raises(ParameterError, match=rf"connector 7 \(particles {i}-{j}\): "
                           f"{message}"):
            run()


def test_explicit_runs_refuse_springs_that_go_soft_in_their_own_strain_range():
    """K(eps) = K0 (1 + 4 eps) <= 0 at eps <= -0.25: per-connector ranges (a release's) are
    validated connector by connector, before the stability limit is computed."""
    model = box_model(K0=50.0, a=200.0)
    lo = np.full(model.n_connectors, -0.2)
    integrator = VerletIntegrator(strain_range=(lo, 0.5))
    integrator.simulate(model, model.state(), 0.5 * integrator.critical_time_step(model), 10)
    lo[3] = -0.3
    i, j = model.edges[3]
    with pytest.raises(ParameterError, match=rf"connector 3 \(particles {i}-{j}\): spring "
                       r"stiffness .* <= 0 in the strain range \[-0\.3, 0\.5\]"):
        VerletIntegrator(strain_range=(lo, 0.5)).simulate(model, model.state(), 1e-5, 10)


def test_divergence_names_a_non_finite_particle_or_the_fastest_one():
    """The checks ride on the kernel's force and position passes; a failed one names the
    step, the time and the particle, never returns NaN. (``simulate`` refuses a non-finite
    state before the run, :func:`test_a_non_finite_state_is_refused_before_the_run`; a
    prepared run's call does not look, so the kernel's check is reached.)"""
    model = box_model()
    dt = 0.5 * critical_time_step(model)
    node = int(model.free_nodes[4])
    state = _perturbed(model, dt, 1e-3)
    state.x[node, 1] = np.nan
    with pytest.raises(StabilityError, match=r"diverged at step 1 \(t = .* s\): particle "
                       r"\d+ has a non-finite position"):
        VerletIntegrator(check_every=1).prepare(model, dt)(state, 10, None, 1e30)
    state = _perturbed(model, dt, 1e-3)
    run = VerletIntegrator(check_every=4).prepare(model, dt)
    with pytest.raises(StabilityError, match=r"diverged at step 4 \(t = .* s\): particle "
                       r"\d+ is the fastest particle; the kinetic energy exceeds 1e-30 J"):
        run(state, 10, None, 1e-30)


def test_a_run_ending_outside_the_strain_range_is_refused_naming_the_connector():
    """The strain checks see the positions a checked step starts from; the state after the
    last step (and its prescribed motion) is checked too: a run whose last step takes a
    connector out of range raises, not returns, naming a connector out of range there."""
    model = box_model()
    dt = 0.5 * critical_time_step(model)
    node = top_centre(model)
    x0 = model.rest_positions[node]
    jump = x0 + [0.0, 0.0, -0.8 * float(model.rest_lengths.mean())]
    motion = Prescribed([node], [0.0, 2 * dt, 3 * dt], [[x0], [x0], [jump]])
    state = model.state()
    with pytest.raises(StabilityError, match=r"connector \d+ \(particles \d+-\d+\) reached "
                       rf"strain .* at the end of the run, t = {3 * dt:.6g} s, outside "
                       r"\[-0\.5, 0\.5\]") as err:
        VerletIntegrator().simulate(model, state, dt, 3, prescribed=motion)
    e = int(str(err.value).split("connector ")[1].split()[0])
    i, j = model.edges[e]
    strain = np.linalg.norm(state.x[j] - state.x[i]) / model.rest_lengths[e] - 1.0
    assert not -0.5 <= strain <= 0.5
    # the same run stopping one step short ends in range and is accepted, and the state it
    # ends in is the one an unmonitored run reaches, bitwise
    state, free = model.state(), model.state()
    VerletIntegrator().simulate(model, state, dt, 2, prescribed=motion)
    VerletIntegrator().simulate(model, free, dt, 2, prescribed=motion, _check_dt=False)
    np.testing.assert_array_equal(state.x, free.x)


@pytest.mark.parametrize("field, index, where", [
    ("x", (40, 0), "particle 40"),
    ("x", (0, 2), r"particle 0 \(fixed\)"),
    ("x_prev", (41, 1), "particle 41"),
    ("arm_force", (3, 1), r"connector 3 \(particles \d+-\d+\)"),
    ("dx_prev", (5,), r"connector 5 \(particles \d+-\d+\)"),
])
def test_a_non_finite_state_is_refused_before_the_run(field, index, where):
    """A NaN put into the state used to surface as a divergence 10 steps later, naming another
    particle and suggesting a smaller step; the run now refuses it before it starts."""
    model = box_model()
    assert model.fixed[0] and not model.fixed[40]
    state = model.state()
    getattr(state, field)[index] = np.nan
    before = state.copy()
    with pytest.raises(ParameterError, match=rf"state\.{field} has non-finite values at {where}"):
        VerletIntegrator().simulate(model, state, 0.5 * critical_time_step(model), 10,
                                    gravity=GRAVITY)
    assert state.t == 0.0
    np.testing.assert_array_equal(state.x, before.x)  # untouched


@pytest.mark.parametrize("gravity, message", [
    (np.array([0.0, -9.81]), r"gravity = \[0\.0, -9\.81\] must be 3 components \(x, y, z\)"),
    ([[0.0, 0.0, -9.81]], r"gravity = \[\[0\.0, 0\.0, -9\.81\]\] must be 3 components"),
    ("down", r"gravity = 'down' must be 3 components"),
    ([0.0, np.inf, 0.0], r"gravity \[0\.0, inf, 0\.0\] m/s\^2 is not finite"),
    (np.array([0.0, 0.0, np.nan]), r"gravity \[0\.0, 0\.0, nan\] m/s\^2 is not finite"),
])
def test_simulate_and_gravity_static_refuse_a_bad_gravity_alike(gravity, message):
    from particle.statics import gravity_static
    model = box_model()
    with pytest.raises(ParameterError, match=message):
        VerletIntegrator().simulate(model, model.state(), 0.5 * critical_time_step(model), 1,
                                    gravity=gravity)
    with pytest.raises(ParameterError, match=message):
        gravity_static(model, gravity)


@pytest.mark.parametrize("n_steps", [2.7, 3.0, -1, "3", None])
def test_a_step_count_that_is_not_a_non_negative_integer_is_refused(n_steps):
    model = box_model()
    with pytest.raises(ParameterError, match=rf"n_steps = {n_steps!r} must be an integer >= 0"):
        VerletIntegrator().simulate(model, model.state(), 0.5 * critical_time_step(model),
                                    n_steps)


def test_numpy_integer_step_counts_are_accepted():
    model = box_model()
    state = model.state()
    dt = 0.5 * critical_time_step(model)
    VerletIntegrator().simulate(model, state, dt, np.int64(3), gravity=GRAVITY)
    assert state.t == pytest.approx(3 * dt)


def test_an_unpickled_model_is_as_immutable_and_typed_as_the_original():
    """Pickle does not keep numpy's write flag: a model sent to a calibration worker gets its
    arrays (and its parameters') frozen again, so it cannot be written to and the kernels
    see the original's types (one compiled specialisation for both), with the same run."""
    import pickle

    import numba

    from tests.test_particle_volume import with_kv
    model = with_kv(box_model((2, 2, 2), a=-20.0, b=300.0), 3000.0, arms=(1500.0, 1000.0))
    copy = pickle.loads(pickle.dumps(model))
    for owner, twin in ((model, copy), (model.params, copy.params)):
        for f in dataclasses.fields(owner):
            value = getattr(twin, f.name)
            if isinstance(value, np.ndarray):
                assert not value.flags.writeable, f.name
                assert numba.typeof(value) == numba.typeof(getattr(owner, f.name)), f.name
                np.testing.assert_array_equal(value, getattr(owner, f.name))
    dt = 0.5 * critical_time_step(model)
    states = [m.state() for m in (model, copy)]
    for m, state in zip((model, copy), states):
        state.x[-1, 2] += 1e-4
        VerletIntegrator().simulate(m, state, dt, 50)
    np.testing.assert_array_equal(states[0].x, states[1].x)
