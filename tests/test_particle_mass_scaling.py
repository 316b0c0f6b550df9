"""Mass scaling: the scaled step is stable (estimate vs bisection), refused above its limit,
statics unchanged, the compiled mass-scaled step equal to the numpy twin, and a one-substep
haptic session that settles to the static indentation force."""
import numpy as np
import pytest

from forcecal.errors import ParameterError, StabilityError
from pipelines.bench.empirical_limit import empirical_critical_step
from particle.evaluators import IndentationEvaluator
from particle.haptics import HapticSession
from particle.integrator import VerletIntegrator
from particle.stability import critical_time_step, inertial_model
from particle.mass_scaling import (ALPHA_TOLERANCE, added_mass_fraction, scaled_inertia,
                                   stiffness_weights)
from particle.reference_numpy import step_numpy
from particle.statics import gravity_static
from tests.particle_models import box_model, deformed_start_and_push, top_centre

GRAVITY = np.array([0.0, 0.0, -9.81])
DOWN = np.array([0.0, 0.0, -1.0])


@pytest.fixture(scope="module")
def model():
    # finer cells along x: the stiffness-to-mass ratio varies, so scaling is selective
    return box_model((5, 3, 2), tau=(0.01, 0.05))


def test_scaled_inertia_reaches_the_step_with_the_least_mass_and_only_where_needed(model):
    limit = critical_time_step(model)
    assert np.array_equal(scaled_inertia(model, 0.9 * limit), model.masses)  # already stable
    dt = 1.2 * limit
    inertia = scaled_inertia(model, dt)
    scaled = critical_time_step(inertial_model(model, inertia))
    assert dt <= scaled
    # the bisection stops within ALPHA_TOLERANCE of the least alpha: 1 % less mass on the
    # scaled particles gives a limit below dt (limit ~ sqrt(mass))
    more = inertia > model.masses
    lighter = np.where(more, np.maximum(model.masses, inertia * (1 - 2 * ALPHA_TOLERANCE)),
                       model.masses)
    assert critical_time_step(inertial_model(model, lighter)) < dt
    assert np.all(inertia >= model.masses) and 0 < more.sum() < (~model.fixed).sum()
    # mass goes to the particles with the most stiffness per mass
    ratio = stiffness_weights(model) / model.masses
    assert ratio[more].min() >= ratio[~more & ~model.fixed].max()
    assert 0.0 < added_mass_fraction(model, inertia) < 1.0


def test_the_scaled_limit_is_below_the_empirical_limit_of_the_scaled_model(model):
    inertia = scaled_inertia(model, 2.0 * critical_time_step(model))
    heavy = inertial_model(model, inertia)
    assert critical_time_step(heavy) <= empirical_critical_step(heavy)


def test_a_step_above_the_scaled_limit_and_a_bad_inertia_are_refused(model):
    dt = 2.0 * critical_time_step(model)
    inertia = scaled_inertia(model, dt)
    scaled = critical_time_step(inertial_model(model, inertia))
    with pytest.raises(StabilityError, match=f"above the stability limit {scaled:.4g} s"):
        HapticSession(model, 1.05 * scaled, period=1.05 * scaled, inertia=inertia)
    with pytest.raises(StabilityError, match="above the stability limit"):
        HapticSession(model, dt, period=dt)  # the same step without the scaling
    light = model.masses.copy()
    light[7] *= 0.5
    with pytest.raises(ParameterError, match="particle 7: inertia .* at least its mass"):
        VerletIntegrator().prepare(model, 0.5 * critical_time_step(model), inertia=light)
    with pytest.raises(ParameterError, match="does not fit"):
        HapticSession(model, dt, period=dt, inertia=inertia[:-1])


def test_inertia_equal_to_the_masses_is_the_default_run_bitwise(model):
    dt = 0.9 * critical_time_step(model)
    runs = []
    for inertia in (None, model.masses.copy()):
        state = model.state()
        VerletIntegrator().simulate(model, state, dt, 300, gravity=GRAVITY, inertia=inertia)
        runs.append(state.x)
    np.testing.assert_array_equal(*runs)


def test_compiled_mass_scaled_step_matches_the_numpy_step(model):
    """Every term (nonlinear springs, arms, gravity, damping, prescribed motion) with inertia."""
    nonlinear = model.with_params(box_model((5, 3, 2), a=-20.0, b=300.0).params)
    dt = 2.0 * critical_time_step(nonlinear, damping=3.0)
    inertia = scaled_inertia(nonlinear, dt, damping=3.0)
    compiled, motion = deformed_start_and_push(nonlinear, dt)
    reference = compiled.copy()
    VerletIntegrator(3.0).simulate(nonlinear, compiled, dt, 50, gravity=GRAVITY,
                                   prescribed=motion, inertia=inertia)
    for _ in range(50):
        step_numpy(nonlinear, reference, dt, gravity=GRAVITY, damping=3.0, prescribed=motion,
                   inertia=inertia)
    scale = np.abs(reference.x - nonlinear.rest_positions).max()
    # same formulas and order; only x/m vs x*(1/m) and the keyframe time differ (an ulp/step)
    np.testing.assert_allclose(compiled.x, reference.x, rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(compiled.arm_force, reference.arm_force, rtol=1e-10,
                               atol=1e-12 * np.abs(reference.arm_force).max())


def test_mass_scaling_keeps_the_static_sag(model):
    """Gravity acts on the physical masses: a damped mass-scaled release settles to the
    Newton equilibrium of the springs (the arms relax: 2 s >> tau = 0.05 s)."""
    dt = 2.0 * critical_time_step(model, damping=60.0)
    inertia = scaled_inertia(model, dt, damping=60.0)
    state = model.state()
    VerletIntegrator(60.0).simulate(model, state, dt, int(2.0 / dt), gravity=GRAVITY,
                                    inertia=inertia)
    sag = gravity_static(model, GRAVITY)
    scale = np.abs(sag).max()
    np.testing.assert_allclose(state.displacement(model), sag, rtol=0, atol=1e-4 * scale)
    # heavier particles under the same gravity would sag more: the scaled sag is the same
    heavy = gravity_static(inertial_model(model, inertia), GRAVITY)
    assert np.abs(heavy - sag).max() > 1e-2 * scale


def test_one_substep_haptic_session_settles_to_the_static_indentation_force(model):
    """Mass scaled to take the whole 1 ms period in one step: the tissue's reaction once
    settled is the static indentation force (inertia does not enter statics)."""
    period = 2.0 * critical_time_step(model, damping=40.0)
    inertia = scaled_inertia(model, period, damping=40.0)
    session = HapticSession(model, period, period=period, damping=40.0, inertia=inertia)
    assert session.substeps == 1
    node = top_centre(model)
    for k in range(int(3.0 / period)):
        force = session.step(node, model.rest_positions[node]
                             + min(1.0, k * period / 0.05) * 0.002 * DOWN)
    static = IndentationEvaluator(model, [node], [DOWN], [0.002]).force_vectors(model.params)
    np.testing.assert_allclose(force, -static[0, 0], rtol=1e-6, atol=1e-9)
