"""One Maxwell-Solid connector against closed-form answers: force law, arms, gravity."""
import logging

import numpy as np
import pytest

from forcecal.schedules import relaxation_schedule
from forcecal.scene import RelaxationSection
from particle import kernels
from particle.evaluators import IndentationEvaluator, RelaxationEvaluator
from particle.guard import energy_bound
from particle.integrator import VerletIntegrator
from particle.model import Prescribed
from particle.stability import critical_time_step
from particle.statics import gravity_static
from particle.params import viscoelastic_params
from tests.particle_models import two_particle_model

L0 = 0.02
K0, A, B = 50.0, -30.0, 400.0
G, TAU = (0.35, 0.25), (0.05, 0.5)


@pytest.mark.parametrize("a, b", [(0.0, 0.0), (A, B)])
def test_static_force_law(a, b):
    """Tension K(eps) dx along the connector, pulling particle i toward j when positive."""
    params = viscoelastic_params(1, K0, a=a, b=b)
    model = two_particle_model(L0, params=params)
    x = np.array([[0.0, 0.0, 0.0], [0.6, 0.0, 0.8]]) * L0 * 1.3  # stretched 30 %, tilted
    forces, tension = np.empty((2, 3)), np.empty(1)
    kernels.internal_forces(x, model.edges, model.rest_lengths, params.K0, params.a, params.b,
                            None, None, None, None, forces, tension, None, np.empty(1))
    dx, eps = 0.3 * L0, 0.3
    expected = (K0 + a * eps + b * eps ** 2) * dx
    assert tension[0] == pytest.approx(expected, rel=1e-13)
    np.testing.assert_allclose(forces[0], expected * np.array([0.6, 0.0, 0.8]), rtol=1e-13)
    np.testing.assert_allclose(forces[1], -forces[0], rtol=0, atol=0)
    # the static evaluator (compression along the inward normal -x) gives K(eps) d with
    # eps = -d/L0; no free particle is left, so the answer is exact to round-off
    depths = np.linspace(0.001, 0.006, 6)
    force = IndentationEvaluator(model, [1], [[-1.0, 0.0, 0.0]], depths)(params)[0]
    eps = -depths / L0
    np.testing.assert_allclose(force, (K0 + a * eps + b * eps ** 2) * depths, rtol=1e-13)


def _step_response(dt: float, n_steps: int, dx0: float) -> np.ndarray:
    """Tension (n_steps,) [N] after each explicit step once particle 1 jumps by dx0 and holds."""
    model = two_particle_model(L0, params=viscoelastic_params(1, K0, g=G, tau=TAU))
    held = Prescribed.hold([1], [[L0 + dx0, 0.0, 0.0]])
    run = VerletIntegrator().prepare(model, dt, prescribed_nodes=[1])
    state = model.state()
    bound = energy_bound(model, state, dt, n_steps, None, held)
    out = np.empty(n_steps)
    for m in range(n_steps):
        run(state, 1, (held.times, held.positions), bound)
        out[m] = -run.force_on(state, 1)[0]  # tension = minus the force on particle j along +x
    return out


def test_relaxation_after_a_step_matches_the_discrete_recursion_exactly():
    """F_arm after m steps of the held jump is k dx0 r^m with r = b/(b + k dt).

    The paper's recursion F^t = r (F^{t-1} + k (dx^t - dx^{t-1})) starts from F = 0,
    sees the jump once (F^1 = k r dx0) and then only decays by r per step.
    """
    dt, dx0, n = 1e-3, 2e-3, 200
    params = viscoelastic_params(1, K0, g=G, tau=TAU)
    k = params.arm_stiffness[0]
    r = params.b1[0] / (params.b1[0] + k[0] * dt), params.b2[0] / (params.b2[0] + k[1] * dt)
    m = np.arange(1, n + 1)
    expected = K0 * dx0 + k[0] * dx0 * r[0] ** m + k[1] * dx0 * r[1] ** m
    np.testing.assert_allclose(_step_response(dt, n, dx0), expected, rtol=1e-13)


def test_discrete_relaxation_converges_linearly_to_the_maxwell_solid():
    """At t = tau_1 the error against K dx + sum k_i dx exp(-t/tau_i) halves with dt."""
    dx0, t = 2e-3, TAU[0]
    params = viscoelastic_params(1, K0, g=G, tau=TAU)
    k = params.arm_stiffness[0]
    exact = K0 * dx0 + dx0 * (k[0] * np.exp(-t / TAU[0]) + k[1] * np.exp(-t / TAU[1]))
    errors = []
    for dt in (1e-3, 5e-4, 2.5e-4, 1.25e-4):
        steps = round(t / dt)
        errors.append(abs(_step_response(dt, steps, dx0)[-1] - exact))
    ratios = np.array(errors[:-1]) / np.array(errors[1:])
    # backward Euler is first order: halving dt halves the error (ratio 2 up to O(dt))
    np.testing.assert_allclose(ratios, 2.0, rtol=0.02)
    assert errors[0] < 0.01 * exact


@pytest.mark.parametrize("a, b", [(0.0, 0.0), (A, B)])
def test_quasi_static_relaxation_is_exact_for_a_single_connector(a, b):
    """The exponential recursion is exact when the elongation is linear within each step.

    One connector whose far end follows the piecewise-linear ramp-and-hold has exactly
    that elongation, so the quasi-static curve equals the continuous Maxwell-Solid:
    arm force k_i tau_i v (1 - exp(-t/tau_i)) on the ramp (rate v), then exponential decay.
    """
    params = viscoelastic_params(1, K0, a=a, b=b, g=G, tau=TAU)
    model = two_particle_model(L0, params=params)
    section = RelaxationSection(depth=0.004, ramp_time=0.1, ramp_steps=5, hold_time=2.5,
                                hold_steps=12)
    times, depths = relaxation_schedule(section)
    curve = RelaxationEvaluator(model, [1], [[-1.0, 0.0, 0.0]], times, depths)(params)[0]
    rate = section.depth / section.ramp_time
    eps = -depths / L0
    expected = (K0 + a * eps + b * eps ** 2) * depths
    for k, tau in zip(params.arm_stiffness[0], TAU):
        on_ramp = k * tau * rate * (1.0 - np.exp(-np.minimum(times, section.ramp_time) / tau))
        expected += on_ramp * np.exp(-np.maximum(times - section.ramp_time, 0.0) / tau)
    np.testing.assert_allclose(curve, expected, rtol=1e-12)


def test_hanging_spring_settles_at_mg_over_k(caplog):
    """A mass on a vertical linear spring comes to rest at elongation m g / K0 (arms relaxed).

    At rest the single spring has no transverse stiffness: the Newton tangent is exactly
    singular and is factorised with a shifted diagonal, which is logged."""
    caplog.set_level(logging.DEBUG, logger="particle.statics")
    mass, g = 0.01, 9.81
    params = viscoelastic_params(1, K0, g=G, tau=(0.01, 0.05))
    model = two_particle_model(L0, mass=mass, params=params, direction=(0.0, 0.0, -1.0))
    gravity = np.array([0.0, 0.0, -g])
    sag = mass * g / K0
    u = gravity_static(model, gravity)
    assert "tangent stiffness exactly singular; factorising it with its diagonal shifted" in (
        caplog.text)
    # Newton converges to round-off for one spring (tolerance 1e-10 of the weight)
    np.testing.assert_allclose(u[1], [0.0, 0.0, -sag], rtol=1e-9, atol=1e-15)
    np.testing.assert_array_equal(u[0], 0.0)
    damping = 60.0  # about critical for omega = sqrt(K/m) ~ 70-110 rad/s
    integrator = VerletIntegrator(damping)
    dt = 0.5 * critical_time_step(model, damping=damping)
    state = model.state()
    # the arms creep out with retardation times below 0.2 s: 10 s leaves < 1e-12 of it
    integrator.simulate(model, state, dt, round(10.0 / dt), gravity=gravity)
    np.testing.assert_allclose(state.x[1] - model.rest_positions[1], [0.0, 0.0, -sag],
                               rtol=1e-9, atol=1e-15)
