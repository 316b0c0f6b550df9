"""Selective mass scaling: more inertia where the stiffness limits the explicit step.

The explicit step is limited by the stiffest particles relative to their mass
(``2/omega_max``, :func:`particle.integrator.critical_time_step`). Mass scaling
gives those particles a larger *inertial* mass, so that a chosen step becomes
stable, while the loads keep the physical masses (gravity ``m g``, damping):
statics are unchanged, the dynamics are slowed where mass was added. It is what
explicit crash and forming codes do for their smallest elements; here it lets a
haptic session take one step per 1 ms device period on meshes whose limit is
below 1 ms. Its cost is an error in the transient response, measured by the
``haptic scale`` benchmark (``pipelines/bench/haptic.py``) against the unscaled
float64 run.

Which particles get mass: particle n's weight is the diagonal of the
kappa-weighted Laplacian, ``w_n = sum of kappa_e over its connectors`` [N/m]
(:func:`~particle.integrator.connector_stiffness_bound`, the per-connector bound
the stability limit is made of); the inertia is ``max(m_n, alpha w_n)`` with the
smallest ``alpha`` [s^2] (found by bisection) for which the rigorous limit of the
scaled model reaches the step. Gershgorin bounds the search: with ``m_n >=
alpha w_n`` everywhere, ``omega_max^2 <= 2/alpha``.
"""

from __future__ import annotations

import logging
import math

import numpy as np

from forcecal.errors import ParameterError
from particle.stability import (DEFAULT_STRAIN_RANGE, EIGENVALUE_MARGIN, check_time_step,
                                connector_stiffness_bound, critical_time_step, inertial_model)
from particle.model import Model
from particle.params import StrainBounds, connector_strain_bounds
from particle.volume_bounds import node_volume_stiffness_bound

log = logging.getLogger(__name__)

# relative width of the final bisection bracket of alpha: the added mass is at most this much
# above the least that reaches the step
ALPHA_TOLERANCE = 0.01


def stiffness_weights(model: Model, strain_range: StrainBounds = DEFAULT_STRAIN_RANGE
                      ) -> np.ndarray:
    """(N,) ``w_n`` = sum of the stiffness bounds kappa_e [N/m] of particle n's connectors.

    Only steers where mass goes; the acceptance test is the rigorous limit. With the
    volume term, its per-particle bound
    (:func:`~particle.volume_bounds.node_volume_stiffness_bound`, the term's part of
    :func:`~particle.integrator.critical_time_step`) is added, so mass goes where the
    volume term stiffens the model (1400-connector liver, kv 8.9 kPa, one substep per
    ms: 140 % mass added without it, 65 % with it).
    """
    lo, hi = connector_strain_bounds(strain_range, model.n_connectors, model.edges)
    kappa = connector_stiffness_bound(model.params, lo, hi)
    weights = np.bincount(model.edges.ravel(), np.repeat(kappa, 2), model.n_particles)
    if model.params.kv is not None:
        weights += node_volume_stiffness_bound(model, lo, hi)
    return weights


def scaled_inertia(model: Model, dt: float, *, strain_range: StrainBounds = DEFAULT_STRAIN_RANGE,
                   damping: float = 0.0) -> np.ndarray:
    """(N,) inertial masses [kg] with which ``dt`` [s] is within the stability limit.

    The limit is :func:`~particle.integrator.critical_time_step` of the model with
    these masses (over ``strain_range``, with mass-proportional ``damping``
    [1/s]), the same rigorous bound every run checks; the physical masses are
    returned (a copy) when ``dt`` is already stable. Only particles whose
    stiffness-to-mass ratio is too high get mass (see the module docstring).
    Raises :class:`~forcecal.errors.StabilityError` for a ``dt`` that is not a
    finite number > 0.
    """
    check_time_step(dt, math.inf)
    masses = model.masses.copy()

    def limit(alpha: float) -> float:
        inertia = np.maximum(masses, alpha * weights)
        return critical_time_step(inertial_model(model, inertia), strain_range=strain_range,
                                  damping=damping)

    if critical_time_step(model, strain_range=strain_range, damping=damping) >= dt:
        return masses
    weights = stiffness_weights(model, strain_range)
    weights[model.fixed] = 0.0  # clamped particles never move: their mass is irrelevant
    # Gershgorin: alpha >= margin dt^2/2 makes omega^2 <= 2 margin/alpha <= 4/dt^2 (undamped)
    high = EIGENVALUE_MARGIN * dt * dt / 2.0
    while limit(high) < dt:  # damping lowers the limit below 2/omega: more mass
        high *= 2.0
        if not math.isfinite(high):
            raise ParameterError(f"mass scaling cannot reach dt = {dt:.4g} s")
    low = 0.0
    while high - low > ALPHA_TOLERANCE * high:
        mid = 0.5 * (low + high)
        if limit(mid) >= dt:
            high = mid
        else:
            low = mid
    inertia = np.maximum(masses, high * weights)
    log.info("mass scaling to dt = %.4g s: %.3g %% mass added on %d of %d particles", dt,
             100.0 * added_mass_fraction(model, inertia), int(np.sum(inertia > masses)),
             model.n_particles)
    return inertia


def added_mass_fraction(model: Model, inertia: np.ndarray) -> float:
    """Inertia added by mass scaling over the free particles, relative to their mass [1]."""
    free = ~model.fixed
    return float(np.sum(inertia[free] - model.masses[free]) / np.sum(model.masses[free]))
