"""Sample schedules of the experiments, shared by the FE and the particle side.

Both sides compute (and the files store) exactly these samples, so curves are
compared point by point without interpolation.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.optimize import brentq

from forcecal.errors import SceneError
from forcecal.scene import IndentationSection, RelaxationSection


def indentation_depths(section: IndentationSection) -> np.ndarray:
    """(S,) float64: depths d_k = depth * k / steps, k = 1..steps [m]."""
    return section.depth * np.arange(1, section.steps + 1) / section.steps


def geometric_ratio(first: float, total: float, n: int) -> float:
    """Ratio r > 1 with first * (1 + r + ... + r^(n-1)) = total (r = 1 if total = n * first)."""
    if total <= n * first * (1 + 1e-12):
        return 1.0
    f = lambda r: first * (r ** n - 1.0) / (r - 1.0) - total
    hi = 2.0
    while f(hi) < 0:
        hi *= 2.0
    return brentq(f, 1.0 + 1e-12, hi, xtol=1e-14)


def relaxation_schedule(section: RelaxationSection) -> tuple[np.ndarray, np.ndarray]:
    """Sample times and prescribed depths of the ramp-and-hold test.

    The ramp (``ramp_steps`` equal steps over ``ramp_time``) is followed by
    ``hold_steps`` steps that start at the ramp's step size and grow
    geometrically so that they end exactly at ``ramp_time + hold_time``: fine
    where the force changes fast (ramp, tau_1), coarse late in the hold.

    Returns:
        time: (S,) float64, sample times [s] (first > 0, increasing).
        depth: (S,) float64, depth at those times [m] (linear ramp, then constant).

    Raises:
        SceneError: the hold steps do not fit in the hold
            (:meth:`~forcecal.scene.RelaxationSection.schedule_error`), or the times would
            not increase.
    """
    problem = section.schedule_error()
    if problem:
        raise SceneError(problem)
    dt0 = section.ramp_time / section.ramp_steps
    ramp = dt0 * np.arange(1, section.ramp_steps + 1)
    r = geometric_ratio(dt0, section.hold_time, section.hold_steps)
    steps = dt0 * r ** np.arange(section.hold_steps)
    hold = section.ramp_time + np.cumsum(steps)
    hold[-1] = section.ramp_time + section.hold_time  # exact end despite round-off
    time = np.concatenate([ramp, hold])
    if not np.all(np.diff(np.r_[0.0, time]) > 0):  # a FE march would skip a sample silently
        raise SceneError(f"relaxation schedule {time.tolist()} does not increase")
    depth = section.depth * np.minimum(time / section.ramp_time, 1.0)
    return time, depth


def record_times(duration: float, record_interval: float) -> np.ndarray:
    """(S,) sample times 0, dt_rec, 2 dt_rec, ... <= duration [s] of the dynamic gravity run."""
    n = int(math.floor(duration / record_interval * (1 + 1e-12)))
    return record_interval * np.arange(n + 1)
