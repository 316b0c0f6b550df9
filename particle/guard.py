"""What stops an explicit run: the divergence bound and the state check.

A :class:`~particle.integrator.Run` checks the state it is given
(:func:`check_state`; ``VerletIntegrator.simulate`` also that it is finite), then the
compiled loop checks every ``check_every`` steps and after the last one
that no position is non-finite, that the kinetic energy stays below
:func:`energy_bound` and that the connector strains (and with the volume term the
tets' volumes) stay in the range the step was verified stable for
(:mod:`particle.stability`), the state the run ends in included (its own pass,
:func:`particle.step_kernels.final_strain_check`); the first failure stops the loop with a code,
which :func:`particle.integrator.exit_error` turns into a
:class:`~forcecal.errors.StabilityError` naming the particle, connector or tet.
"""

from __future__ import annotations

import math

import numpy as np

from forcecal.errors import ParameterError
from particle.model import Model, Prescribed, State
from particle.params import connector_name
from particle.nodal_volume import element_arm_energy, element_energy
from particle.statics import check_stiffness, check_volumes
from particle.volume import node_volume_stiffness, tet_name

# the kinetic energy may exceed the work the loads can do by this factor before a run is
# declared divergent: a real run stays far below, an unstable one grows exponentially
ENERGY_MARGIN = 100.0


def energy_bound(model: Model, state: State, dt: float, n_steps: int,
                 gravity: np.ndarray | None, prescribed: Prescribed | None) -> float:
    """Kinetic energy [J] above which a run is declared divergent.

    ``ENERGY_MARGIN`` x (present kinetic + elastic energy + the work gravity can
    do in the run (falling the model's size, or freely for the run's duration)
    + the work prescribed motion can do (moving each prescribed node its
    largest keyframe distance against its connectors, plus dragging the whole
    mass at the keyframes' fastest speed)), plus a floor for runs at rest. The
    elastic energy is ``K(eps) dx^2/2`` at the state's strains; a state where
    a spring's K(eps) <= 0 raises :class:`ParameterError`.
    """
    m = model.masses
    p = model.params
    size = float(np.linalg.norm(np.ptp(model.rest_positions, axis=0)))
    total_mass = float(m.sum())
    duration = n_steps * dt
    v_prev = (state.x - state.x_prev) / (state.dt or dt)
    energy = 0.5 * float(np.sum(m[:, None] * v_prev ** 2))
    lengths = np.linalg.norm(state.x[model.edges[:, 1]] - state.x[model.edges[:, 0]], axis=1)
    dx = lengths - model.rest_lengths
    strain = np.clip(dx / model.rest_lengths, -0.99, None)
    # prepare() refused springs that go soft in the run's strain range; a state outside it
    # (an unmonitored run) where one does is refused too, not bounded with |K|
    check_stiffness(model, strain, f"explicit run from t = {state.t:.6g} s")
    energy += float(np.sum(0.5 * p.stiffness(strain) * dx ** 2))
    if p.kv is not None:
        check_volumes(model, state.x, f"explicit run from t = {state.t:.6g} s")
        energy += element_energy(model, state.x)
    energy += float(np.sum(state.arm_force ** 2 / (2.0 * p.arm_stiffness)))
    if p.has_volume_arms:
        energy += element_arm_energy(model, state.volume_arm)
    if gravity is not None:
        g = float(np.linalg.norm(gravity))
        energy += total_mass * g * (size + 0.5 * g * duration ** 2)
    if prescribed is not None:
        stiff = np.bincount(model.edges.ravel(), np.repeat(p.K0 + p.k1 + p.k2, 2),
                            model.n_particles)
        if p.kv is not None:
            stiff = stiff + node_volume_stiffness(model)
        stiff = stiff[prescribed.nodes]
        reach = np.linalg.norm(prescribed.positions - state.x[prescribed.nodes][None], axis=2)
        energy += float(np.sum(stiff * (reach.max(axis=0) + size) ** 2))
        if len(prescribed.times) > 1:
            speed = (np.linalg.norm(np.diff(prescribed.positions, axis=0), axis=2)
                     / np.diff(prescribed.times)[:, None]).max()
            energy += total_mass * float(speed) ** 2
    floor = 0.5 * total_mass * (1e-6 * size / dt) ** 2
    return ENERGY_MARGIN * energy + floor


def check_state(model: Model, state: State, *, finite: bool = False) -> None:
    """Raise :class:`ParameterError` unless ``state`` fits ``model`` and the kernels.

    Its arrays must have the model's shapes and be C-contiguous, writeable
    float64 (another dtype would be truncated to it or compile another kernel
    specialisation), and its time finite; with the volume term's arms, it must hold
    their pressures and volume strains (``volume_arm`` (M, 2), ``volume_prev`` (M,), M the
    model's :attr:`~particle.model.Model.n_volume_elements`: its tets, or its particles for
    the nodal term).
    With ``finite`` (at the start of a run: one
    numpy pass over the state, so not on every haptic call) its arrays must hold finite
    values too: a NaN put into the state would otherwise surface as a divergence steps
    later, naming another particle and suggesting a smaller step.
    """
    shapes = (("x", (model.n_particles, 3)), ("x_prev", (model.n_particles, 3)),
              ("arm_force", (model.n_connectors, 2)), ("dx_prev", (model.n_connectors,)))
    if model.params.has_volume_arms:
        rows = model.n_volume_elements
        shapes += (("volume_arm", (rows, 2)), ("volume_prev", (rows,)))
    for name, shape in shapes:
        arr = getattr(state, name)
        if arr is None:
            raise ParameterError(f"the state has no {name}: this model's volume term has "
                                 "arms, whose state a run needs (make it with model.state())")
        if not (isinstance(arr, np.ndarray) and arr.shape == shape
                and arr.dtype == np.float64 and arr.flags.carray):
            what = (f"{arr.dtype} array of shape {arr.shape}" if isinstance(arr, np.ndarray)
                    else type(arr).__name__)
            raise ParameterError(
                f"the state's {name} ({what}) does not belong to this model of "
                f"{model.n_particles} particles and {model.n_connectors} connectors:"
                f" expected a writeable, C-contiguous float64 array of shape {shape}")
    if not math.isfinite(state.t):
        raise ParameterError(f"the state's time t = {state.t} s is not finite")
    if finite:
        check_finite_state(model, state)


def check_finite_state(model: Model, state: State) -> None:
    """Raise :class:`ParameterError` naming the first particles (x, x_prev), connectors
    (arm_force, dx_prev) or tets (volume_arm, volume_prev, with the volume arms) where
    ``state`` (shapes already checked) holds NaN or inf."""
    arrays = (("x", "particle"), ("x_prev", "particle"), ("arm_force", "connector"),
              ("dx_prev", "connector"))
    if model.params.has_volume_arms:
        arrays += (("volume_arm", "tet"), ("volume_prev", "tet"))
    for name, what in arrays:
        arr = getattr(state, name)
        ok = np.isfinite(arr)
        if ok.all():
            continue
        bad = np.nonzero(~ok if ok.ndim == 1 else ~ok.all(axis=1))[0]
        first = int(bad[0])
        if what == "particle":
            name_first = f"particle {first}" + (" (fixed)" if model.fixed[first] else "")
        elif what == "tet":
            name_first = tet_name(first, model.tets)
        else:
            name_first = connector_name(first, model.edges)
        more = f" and {len(bad) - 1} more {what}(s)" if len(bad) > 1 else ""
        raise ParameterError(f"state.{name} has non-finite values at {name_first}{more}; "
                             "a run needs a finite state (e.g. model.state())")
