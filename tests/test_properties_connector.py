"""Property-based tests (hypothesis) of the Maxwell-Solid connector law over its parameter space.

One connector, particle 0 clamped, particle 1 moved: tension continuous in the
elongation and of its sign, relaxation after a ramp monotone with the arms
vanishing, the explicit (backward-Euler) arm recursion converging to the
continuous law at first order, and the arm recursion a contraction for every
step. Derandomized, so CI sees the same examples every run.
"""
import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from particle import kernels
from particle.evaluators import RelaxationEvaluator
from particle.experiments import relaxation_dynamic
from particle.stability import critical_time_step
from particle.params import ConnectorParams
from tests.particle_models import two_particle_model

L0 = 0.02  # m
SETTINGS = settings(deadline=None, max_examples=40, derandomize=True)


@st.composite
def connectors(draw, strain: float = 0.5) -> ConnectorParams:
    """Parameters whose spring K(eps) stays > 0 on [-strain, strain]; arms of any strength."""
    K0 = draw(st.floats(1.0, 1e3))
    a = K0 * draw(st.floats(-1.5, 1.5))
    b = K0 * draw(st.one_of(st.just(0.0), st.floats(1e-3, 50.0)))
    k1, k2 = (K0 * draw(st.floats(0.05, 10.0)) for _ in range(2))
    tau1, tau2 = (draw(st.floats(1e-3, 10.0)) for _ in range(2))
    params = ConnectorParams.uniform(1, K0=K0, a=a, b=b, k1=k1, b1=tau1 * k1, k2=k2,
                                     b2=tau2 * k2)
    assume(params.extreme_stiffness((-strain, strain))[0][0] > 0.0)
    return params


def _direction(draw_vector) -> np.ndarray:
    v = np.asarray(draw_vector, dtype=float)
    assume(np.linalg.norm(v) > 0.1)
    return v / np.linalg.norm(v)


def spring_force(params: ConnectorParams, dx: float, direction: np.ndarray) -> np.ndarray:
    """(2, 3) forces [N] of the compiled kernel on both particles at elongation ``dx`` (no arms)."""
    x = np.array([np.zeros(3), (L0 + dx) * direction])
    forces = np.empty((2, 3))
    kernels.internal_forces(x, np.array([[0, 1]]), np.array([L0]), params.K0, params.a,
                            params.b, None, None, None, None, forces, np.empty(1), None,
                            np.empty(1))
    return forces


vectors = st.tuples(*(st.floats(-1.0, 1.0),) * 3)


@SETTINGS
@given(connectors(), st.floats(-0.45, 0.45), st.floats(-1e-3, 1e-3), vectors)
def test_tension_is_continuous_in_the_elongation(params, strain, step, vector):
    """|F(dx + h) - F(dx)| <= max |dF/d(dx)| |h|: Lipschitz, tangent K0 + 2 a eps + 3 b eps^2."""
    e = _direction(vector)
    dx, h = strain * L0, step * L0
    change = np.linalg.norm(spring_force(params, dx + h, e)[1] - spring_force(params, dx, e)[1])
    lo, hi = sorted((strain, strain + step))
    lipschitz = float(np.max(np.abs(params.extreme_tangent_stiffness((lo, hi)))))
    roundoff = 1e-12 * lipschitz * L0
    assert change <= lipschitz * abs(h) * (1 + 1e-9) + roundoff


@SETTINGS
@given(connectors(), st.floats(-0.5, 0.5).filter(lambda s: abs(s) > 1e-9), vectors)
def test_tension_has_the_sign_of_the_elongation(params, strain, vector):
    """With K(eps) > 0 a stretched connector pulls its ends together, a compressed one pushes."""
    e = _direction(vector)
    forces = spring_force(params, strain * L0, e)
    along = forces[0] @ e  # force on particle 0 along 0 -> 1: the tension
    assert np.sign(along) == np.sign(strain)
    expected = float(params.stiffness(np.array([strain]))[0]) * strain * L0
    assert along == pytest.approx(expected, rel=1e-12)
    np.testing.assert_array_equal(forces[1], -forces[0])  # action = reaction


def _ramp_and_hold(ramp_time: float, depth: float, hold: float, ramp_samples: int = 4,
                   hold_samples: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """(times, depths): a linear ramp to ``depth`` sampled evenly, then a geometric hold."""
    ramp = ramp_time * np.arange(1, ramp_samples + 1) / ramp_samples
    held = ramp_time + np.geomspace(1e-3 * hold, hold, hold_samples)
    times = np.r_[ramp, held]
    return times, np.minimum(times / ramp_time, 1.0) * depth


@SETTINGS
@given(connectors(), st.floats(0.01, 0.4), st.floats(1e-3, 1.0))
def test_relaxation_after_the_ramp_is_monotone_and_the_arms_vanish(params, strain, ramp_time):
    """While the depth is held the arm forces decay (F_arm(t + s) = exp(-s/tau) F_arm(t)), so
    the indenter force falls monotonically to the spring's K(eps) d once t >> tau_max."""
    model = two_particle_model(L0, params=params)
    depth = strain * L0
    hold = 40.0 * float(params.arm_tau.max())
    times, depths = _ramp_and_hold(ramp_time, depth, hold)
    force = RelaxationEvaluator(model, [1], [[-1.0, 0.0, 0.0]], times, depths)(params)[0]
    held = force[times >= ramp_time]
    scale = float(force.max())
    assert np.all(np.diff(held) <= 1e-12 * scale)
    spring = float(params.stiffness(np.array([-strain]))[0]) * depth
    # what is left of the arms after 40 tau_max is < k_i d exp(-40) ~ 4e-18 k_i d
    assert held[-1] == pytest.approx(spring, rel=1e-9)
    assert force.max() >= spring  # the arms added force while they were loaded


@settings(deadline=None, max_examples=15, derandomize=True)
@given(connectors(), st.floats(0.05, 0.4), st.integers(1, 5))
def test_explicit_arm_recursion_converges_to_the_continuous_law_at_first_order(params, strain,
                                                                               ramp_in_tau):
    """Explicit runs use backward Euler for the arms; the quasi-static evaluator integrates them
    exactly for a piecewise-linear elongation (the continuous Maxwell-Solid here).

    At a constant step, backward Euler's error on dF/dt = k v - F/tau is bounded by
    k v dt/2 (local error <= k v dt^2/(2 tau), damped by r = tau/(tau + dt) per step,
    since |dF/dt| <= k v on ramp and hold), and it is first order: halving dt about
    halves it. Samples are evenly spaced (every tau_min/2), so the explicit run keeps
    one step throughout.
    """
    tau_min = float(params.arm_tau.min())
    assume(params.arm_tau.max() <= 20.0 * tau_min)  # bounded step counts (< 2500 per run)
    model = two_particle_model(L0, params=params)
    depth = strain * L0
    ramp_time = ramp_in_tau * tau_min
    times = 0.5 * tau_min * np.arange(1, int(2 * ramp_in_tau + 4 * params.arm_tau.max()
                                               / tau_min) + 1)
    depths = np.minimum(times / ramp_time, 1.0) * depth
    exact = RelaxationEvaluator(model, [1], [[-1.0, 0.0, 0.0]], times, depths)(params)[0]
    rate = depth / ramp_time
    errors = []
    # the moved particle has a mass, so the explicit step also obeys the stability limit
    coarse = min(0.04 * tau_min, 0.5 * critical_time_step(model))
    for dt in (coarse, coarse / 2):
        explicit = -relaxation_dynamic(model, 1, np.array([-1.0, 0.0, 0.0]), times, depths, dt,
                                       progress=False)[:, 0]
        error = float(np.abs(explicit - exact).max())
        assert error <= float(params.arm_stiffness.sum()) * rate * dt / 2 * (1 + 1e-6)
        errors.append(error)
    # first order up to O(dt/tau) = 4 % corrections
    assert errors[1] / errors[0] == pytest.approx(0.5, abs=0.05)


@SETTINGS
@given(connectors(), st.floats(1e-9, 1e3))
def test_arm_recursions_are_contractions_for_every_step(params, dt):
    """0 <= r < 1 and c > 0 for both recursions: an arm left alone decays, unconditionally
    (r underflows to 0 for dt >> tau), and backward Euler (r = 1/(1 + dt/tau)) decays no
    faster than the exact exp(-dt/tau)."""
    r_be, c_be = params.arm_recursion(dt)
    r_ex, c_ex = params.arm_recursion(dt, exact=True)
    for r, c in ((r_be, c_be), (r_ex, c_ex)):
        assert np.all((r >= 0) & (r < 1)) and np.all(c > 0)
    assert np.all(r_be >= r_ex - 4 * np.finfo(float).eps)  # they differ by (dt/tau)^2/2: rounding


@settings(deadline=None, max_examples=15, derandomize=True)
@given(connectors(), st.floats(0.05, 0.4), st.floats(1.0, 5.0))
def test_explicit_relaxation_with_changing_steps_keeps_the_same_error_bound(params, strain,
                                                                          ramp_in_tau):
    """Samples on a geometric hold: the explicit run changes its step at every sample. Each
    step's arm update must use that step's coefficients, so the bound k v dt_max/2 still holds
    (the error recursion e_n = r_n e_{n-1} + r_n dt_n^2 k v/(2 tau) keeps it for dt_n <= dt_max)."""
    tau_min = float(params.arm_tau.min())
    assume(params.arm_tau.max() <= 20.0 * tau_min)
    model = two_particle_model(L0, params=params)
    depth = strain * L0
    ramp_time = ramp_in_tau * tau_min
    times, depths = _ramp_and_hold(ramp_time, depth, 2.0 * float(params.arm_tau.max()),
                                   hold_samples=8)
    exact = RelaxationEvaluator(model, [1], [[-1.0, 0.0, 0.0]], times, depths)(params)[0]
    dt = min(0.04 * tau_min, 0.5 * critical_time_step(model))
    explicit = -relaxation_dynamic(model, 1, np.array([-1.0, 0.0, 0.0]), times, depths, dt,
                                   progress=False)[:, 0]
    bound = float(params.arm_stiffness.sum()) * depth / ramp_time * dt / 2
    assert np.abs(explicit - exact).max() <= bound * (1 + 1e-6)
