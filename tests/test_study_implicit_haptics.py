"""The implicit haptic step of the study (studies/_implicit_step.py): its physics on tiny models
with closed forms (its speed is the study's measurement, not a test's)."""
import math

import numpy as np
import pytest

from forcecal.errors import MeshError, ParameterError
from particle.model import ModelBuilder
from particle.params import ConnectorParams, viscoelastic_params
from studies._implicit_step import NEWMARK, ImplicitSession, Scheme
from studies.implicit_haptics import analytic_damping, frozen_amplification

H = 1e-3  # s
MASS, K0, L = 1e-3, 30.0, 0.01  # kg, N/m, m: omega = 173 rad/s, omega h = 0.17


def chain(n: int, params: ConnectorParams | None = None):
    """Particles 0..n-1 along x, ``L`` apart, particle 0 fixed; connectors between
    neighbours (linear springs ``K0`` unless ``params``)."""
    builder = ModelBuilder()
    for k in range(n):
        builder.add_particle((k * L, 0.0, 0.0), MASS, fixed=k == 0)
    builder.add_connectors(np.column_stack([np.arange(n - 1), np.arange(1, n)]))
    if params is None:
        params = ConnectorParams.uniform(n - 1, K0=K0, k1=1.0, b1=1.0, k2=1.0, b2=1.0)
    return builder.finalize(params)


def energy(session, gravity):
    """Kinetic + spring + gravity potential energy [J] of an arm-free linear-spring chain."""
    m = session.model
    dx = np.linalg.norm(session.x[m.edges[:, 1]] - session.x[m.edges[:, 0]], axis=1) - L
    u = session.x - m.rest_positions
    return float(0.5 * np.sum(m.masses[:, None] * session.v ** 2) + 0.5 * K0 * np.sum(dx ** 2)
                 - np.sum(m.masses[:, None] * u * gravity))


def test_newmark_keeps_the_energy_of_a_linear_network_to_round_off():
    """Five springs pulled along their axis from rest (they stay stretched: the forces are
    linear in the positions), 2000 steps: the trapezoidal rule keeps the quadratic energy
    exactly, and one linearised solve per step is the exact step for a linear network. The
    energy swings between kinetic and elastic by ~its size; round-off only (1e-12)."""
    gravity = np.array([5.0, 0.0, 0.0])
    session = ImplicitSession(chain(6), NEWMARK, gravity=gravity, arms=False)
    start = energy(session, gravity)
    kinetic, drift = [], []
    for _ in range(2000):
        session.advance()
        drift.append(energy(session, gravity) - start)
        kinetic.append(0.5 * np.sum(session.model.masses[:, None] * session.v ** 2))
    scale = max(kinetic)
    assert scale > 1e-6  # it moves: ~1e-5 J
    assert np.max(np.abs(drift)) < 1e-12 * scale
    assert np.all(session.x[:, 1:] == 0.0)  # along its axis only, exactly


def test_one_connector_oscillates_with_the_schemes_closed_forms():
    """One free particle on one spring, released from rest under a load along the spring:
    Newmark's x_n = x_eq (1 - cos(n theta)), theta = 2 atan(omega h / 2), to round-off (its
    period error (omega h)^2 / 12 to leading order, 2.5e-3 here, what analytic_damping
    states); backward Euler's recurrence (its amplitude (1 + (omega h)^2)^(-n/2): 1e-5 left
    after 1000 steps); HHT-alpha keeps nearly all
    of it at omega h = 0.17 and a converged step (4 solves) is the same step."""
    g = 5.0
    omega = math.sqrt(K0 / MASS)
    x_eq = MASS * g / K0
    n = np.arange(1, 1001)
    model = chain(2)

    def run(scheme):
        session = ImplicitSession(model, scheme, gravity=np.array([g, 0.0, 0.0]), arms=False)
        out = []
        for _ in n:
            session.advance()
            out.append(session.x[1, 0] - L)
        return np.array(out)

    newmark = run(NEWMARK)
    theta = 2.0 * math.atan(0.5 * omega * H)
    assert np.max(np.abs(newmark - x_eq * (1.0 - np.cos(n * theta)))) < 1e-11 * x_eq
    period_error = analytic_damping(omega / (2.0 * math.pi), H)["newmark_period_error"]
    assert period_error == pytest.approx(2.0 * math.pi / theta / (2.0 * math.pi / (omega * H))
                                         - 1.0, rel=1e-12)
    assert period_error == pytest.approx((omega * H) ** 2 / 12.0, rel=0.01)
    # backward Euler: y = x - x_eq, (y, v)_{n+1} = A^-1 (y, v)_n, A = [[1, -h], [h w^2, 1]]
    # (eigenvalues 1/(1 -+ i omega h): the amplitude shrinks by (1 + (omega h)^2)^(-1/2))
    euler = run(Scheme("backward euler", euler=True)) - x_eq
    step = np.linalg.inv(np.array([[1.0, -H], [H * omega ** 2, 1.0]]))
    y, expected = np.array([-x_eq, 0.0]), []
    for _ in n:
        y = step @ y
        expected.append(y[0])
    assert np.max(np.abs(euler - expected)) < 1e-11 * x_eq
    assert np.abs(euler[-200:]).max() < (1.0 + (omega * H) ** 2) ** (-400) * x_eq
    hht = run(Scheme("hht", alpha=-0.05)) - x_eq
    assert 0.99 * x_eq < np.abs(hht[-200:]).max() < x_eq
    converged = run(Scheme("converged", iterations=4))
    assert np.max(np.abs(converged - newmark)) < 1e-12 * L  # round-off of positions ~L


def test_the_fixed_point_is_the_exact_nonlinear_equilibrium():
    """A softening two-spring chain with Maxwell arms, its end (the tool) pulled 2 mm along the
    axis and held: the rest tangent is not the tangent there (K0 + a eps: 0.84 K0), yet the
    arms relax, the motion dies out, and the state is the nonlinear equilibrium: the middle
    particle halfway, the tool force -(K0 + a eps) dx exactly (to 1e-9)."""
    a = -2.0 * K0
    params = viscoelastic_params(2, K0, a=a, tau=(0.01, 0.02))
    model = chain(3, params)
    session = ImplicitSession(model, NEWMARK)
    d = 0.002
    target = model.rest_positions[2] + [d, 0.0, 0.0]
    for _ in range(4000):
        force = session.step(2, target)
    dx = d / 2
    eps = dx / L
    assert session.x[1, 0] - L == pytest.approx(dx, rel=1e-9)
    assert force == pytest.approx([-(K0 + a * eps) * dx, 0.0, 0.0], rel=1e-9, abs=1e-15)


def test_a_step_frozen_at_another_tangent_grows_stiffer_modes_and_damps_softer_ones():
    """The one-dof recurrence of the linearised step: exact (radius 1) for Newmark when the
    factorised stiffness is the state's, backward Euler's closed form 1/sqrt(1 + (omega h)^2)
    whatever the mismatch (its eigenvalues' product does not depend on it), above 1 for a
    stiffer state and below for a softer one (the 12k liver's divergence)."""
    euler = Scheme("backward euler", euler=True)
    for wh in (0.03, 1.0, 3.0):
        assert frozen_amplification(NEWMARK, 1.0, wh) == pytest.approx(1.0, abs=1e-12)
        for ratio in (0.8, 1.2):
            assert frozen_amplification(euler, ratio, wh) == pytest.approx(
                (1.0 + wh * wh) ** -0.5, rel=1e-12)
        assert frozen_amplification(NEWMARK, 1.05, wh) > 1.0 > frozen_amplification(
            NEWMARK, 0.95, wh)
    assert frozen_amplification(NEWMARK, 1.05, 1.0) == pytest.approx(1.0157, abs=1e-4)


def test_bad_input_is_refused():
    model = chain(3)
    session = ImplicitSession(model, NEWMARK)
    with pytest.raises(MeshError, match="not a free particle"):
        session.step(0, model.rest_positions[0])
    with pytest.raises(ParameterError, match="3 finite"):
        session.step(2, [0.0, np.nan, 0.0])
    with pytest.raises(ParameterError, match="alpha"):
        Scheme("too damped", alpha=-0.5)
    with pytest.raises(ParameterError, match="> 0"):
        ImplicitSession(model, NEWMARK, period=0.0)
