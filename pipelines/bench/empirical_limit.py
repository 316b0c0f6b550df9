"""The empirical stable-step limit: a bisection over real runs of the integrator.

What :func:`particle.stability.critical_time_step` (a rigorous bound) is checked
against by the tests and ``make bench`` (:mod:`pipelines.bench.stability`). A run of
``steps`` steps from a slightly perturbed state is *blown up* when the integrator's
divergence guard fires (a non-finite position, or kinetic energy beyond
:func:`particle.guard.energy_bound`, 100 x the energy the start state and the loads
hold). Just above the true limit the unstable mode grows by ``1 + sqrt(8 delta)`` per
step (central difference with ``omega dt = 2 (1 + delta)``), so 3000 steps amplify the
energy 100 x as soon as ``delta`` exceeds ~1e-7: the bisection's tolerance, not the run
length, sets the resolution of :func:`empirical_critical_step`.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from forcecal.errors import StabilityError
from particle.integrator import VerletIntegrator
from particle.model import Model, State
from particle.stability import critical_time_step


def perturbed_state(model: Model, amplitude: float, seed: int = 0,
                    prestrain: float = 0.0) -> State:
    """A state at rest, dilated by ``1 + prestrain`` about the centroid, then perturbed.

    Every particle (clamped ones too) is dilated, so every connector starts at
    strain ``prestrain`` with unloaded arms; the free particles are then moved
    randomly by ``amplitude`` x the model's size.
    """
    rng = np.random.default_rng(seed)
    state = model.state()
    centre = model.rest_positions.mean(axis=0)
    state.x[:] = centre + (1.0 + prestrain) * (model.rest_positions - centre)
    state.dx_prev[:] = prestrain * model.rest_lengths
    size = float(np.ptp(model.rest_positions))
    free = model.free_nodes
    state.x[free] += amplitude * size * rng.standard_normal((len(free), 3))
    state.x_prev[:] = state.x
    return state


def blows_up(model: Model, dt: float, *, steps: int = 3000, amplitude: float = 1e-6,
             seed: int = 0, prestrain: float = 0.0, gravity: np.ndarray | None = None) -> bool:
    """Whether ``steps`` explicit steps of ``dt`` [s] from a perturbed state diverge
    (under ``gravity`` [m/s^2] if given)."""
    state = perturbed_state(model, amplitude, seed, prestrain)
    try:
        VerletIntegrator().simulate(model, state, dt, steps, gravity=gravity, _check_dt=False)
    except StabilityError:
        return True
    return False


def bisect(unstable: Callable[[float], bool], stable: float, *, rel_tol: float = 1e-3,
           max_growth: int = 12) -> float:
    """Boundary [s] between stable and unstable steps, starting from a ``stable`` step.

    Doubles until a step is unstable (at most ``max_growth`` times: a model
    that never blows up then reports that bound), then bisects to ``rel_tol``.
    Every loop is bounded, so this cannot hang.
    """
    if unstable(stable):
        raise StabilityError(f"the starting step {stable:.4g} s is already unstable")
    lo, hi = stable, 2.0 * stable
    for _ in range(max_growth):
        if unstable(hi):
            break
        lo, hi = hi, 2.0 * hi
    else:
        return lo
    while hi - lo > rel_tol * lo:
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if unstable(mid) else (mid, hi)
    return lo


def empirical_critical_step(model: Model, *, steps: int = 3000, rel_tol: float = 1e-3,
                            seed: int = 0, prestrain: float = 0.0) -> float:
    """Largest stable explicit step [s] found by bisection (module docstring).

    ``prestrain``: the run starts dilated (:func:`perturbed_state`); with every
    surface particle clamped a uniform dilation of a Kuhn box is an equilibrium
    (each interior particle's connectors come in opposite pairs), so the limit
    found is the one of the tangent at that strain. Starts from the estimate
    :func:`critical_time_step` x 0.5, which must be stable.
    """
    return bisect(lambda dt: blows_up(model, dt, steps=steps, seed=seed, prestrain=prestrain),
                  0.5 * critical_time_step(model), rel_tol=rel_tol)
