"""Plain-numpy explicit step: the reference the compiled kernels are tested and benchmarked against.

The same model, formulas and order of operations as
:func:`particle.step_kernels.run_verlet` (see :class:`particle.integrator.VerletIntegrator`),
written with whole-array numpy operations instead of loops: :func:`step_numpy` is
:func:`forces_numpy` (every force term at the present state) followed by the update.
"""

from __future__ import annotations

import numpy as np

from particle.model import Model, Prescribed, State
from particle.nodal_volume import (element_arm_recursion, element_coefficients, element_strains,
                                   nodal_volume_forces_numpy)
from particle.volume import volume_arm_pressures_numpy, volume_forces_numpy


def step_numpy(model: Model, state: State, dt: float, *, gravity: np.ndarray | None = None,
               damping: float = 0.0, arms: bool = True,
               prescribed: Prescribed | None = None, inertia: np.ndarray | None = None) -> None:
    """Advance ``state`` by one position-Verlet step of ``dt`` [s] in place.

    A state that was never stepped (``state.dt is None``) takes the start-up
    step from rest, ``x^1 = x^0 + dt^2/2 a^0``. ``state.dt`` must otherwise equal ``dt``.
    ``prescribed`` particles are moved to their keyframe positions at ``t + dt``
    instead of being integrated. ``inertia`` (N,) [kg]: mass scaling, the masses the
    update divides by (the loads keep the physical masses).
    """
    if state.dt is not None and state.dt != dt:
        raise ValueError("step_numpy does not change the step size of a running state")
    forces = forces_numpy(model, state, dt, gravity=gravity, damping=damping, arms=arms)
    x, x_prev = state.x, state.x_prev
    m = model.masses[:, None]
    scale = 0.5 if state.dt is None else 1.0
    free = model.free_nodes if prescribed is None else np.setdiff1d(model.free_nodes,
                                                                     prescribed.nodes)
    inertial = m if inertia is None else np.asarray(inertia)[:, None]
    new = 2.0 * x[free] - x_prev[free] + scale * dt * dt * forces[free] / inertial[free]
    x_prev[free] = x[free]
    x[free] = new
    if prescribed is not None:
        nodes, times, keys = prescribed.nodes, prescribed.times, prescribed.positions
        t = state.t + dt
        k = int(np.searchsorted(times, t))
        if k == 0 or k >= len(times):
            target = keys[min(k, len(times) - 1)]
        else:
            w = (t - times[k - 1]) / (times[k] - times[k - 1])
            target = (1.0 - w) * keys[k - 1] + w * keys[k]
        x_prev[nodes] = x[nodes]
        x[nodes] = target
    state.t += dt
    state.dt = dt


def forces_numpy(model: Model, state: State, dt: float, *, gravity: np.ndarray | None = None,
                 damping: float = 0.0, arms: bool = True) -> np.ndarray:
    """(N, 3) net force [N] on every particle at ``state``, for a step of ``dt`` [s].

    Connectors (with the arms advanced by the paper's recursion for ``dt``: this updates
    ``state.arm_force`` and ``state.dx_prev``), the volume term (its arms likewise:
    ``state.volume_arm``, ``state.volume_prev``), gravity ``m g`` and the
    mass-proportional damping ``-m damping/dt (x - x_prev)``.
    """
    p = model.params
    x, x_prev = state.x, state.x_prev
    i, j = model.edges[:, 0], model.edges[:, 1]
    d = x[j] - x[i]
    length = np.sqrt(np.einsum("ij,ij->i", d, d))
    dx = length - model.rest_lengths
    tension = p.stiffness(dx / model.rest_lengths) * dx
    if arms:
        r, c = p.arm_recursion(dt)
        state.arm_force[:] = r * state.arm_force + c * (dx - state.dx_prev)[:, None]
        tension = tension + state.arm_force.sum(axis=1)
    state.dx_prev[:] = dx
    pull = (tension / length)[:, None] * d
    forces = np.zeros_like(x)
    np.add.at(forces, i, pull)
    np.add.at(forces, j, -pull)
    if p.kv is not None:
        forces += volume_forces_of(model, state, dt, arms)
    m = model.masses[:, None]
    if gravity is not None:
        forces += m * np.asarray(gravity)
    if damping:
        forces -= m * (damping / dt) * (x - x_prev)
    return forces


def volume_forces_of(model: Model, state: State, dt: float, arms: bool) -> np.ndarray:
    """(N, 3) the volume term's forces [N] at ``state.x``, per tet or nodal
    (``model.volume_element``), its arms (if any and ``arms``) advanced by the paper's
    recursion for ``dt`` into ``state.volume_arm``, ``state.volume_prev``."""
    p, x = model.params, state.x
    pressure = None
    if p.has_volume_arms and arms:
        strain = element_strains(model, x)
        r, c = element_arm_recursion(model, dt)
        state.volume_arm[:] = volume_arm_pressures_numpy(strain, r, c, state.volume_arm,
                                                         state.volume_prev)
        state.volume_prev[:] = strain
        pressure = state.volume_arm.sum(axis=1)
    if model.volume_element == "nodal":
        return nodal_volume_forces_numpy(x, model.tets, *element_coefficients(model), pressure)
    return volume_forces_numpy(x, model.tets, model.rest_volumes, p.kv, pressure)
