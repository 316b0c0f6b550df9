"""Error measures between simulated and reference force curves.

Two numbers, defined once for the whole project:

* the paper's cost ``G_j = sum_i (F_ref,i - F_sim,i)^2`` of test point j over its
  curve samples [N^2] (what the optimisers minimise, summed over calibration points);
* the relative RMS error ``RMS(F_sim - F_ref) / max|F_ref|`` of each point [1]
  (what every report quotes).
"""

from __future__ import annotations

import numpy as np

from forcecal.errors import ParameterError


def _pair(sim: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    sim = np.atleast_2d(np.asarray(sim, dtype=np.float64))
    ref = np.atleast_2d(np.asarray(ref, dtype=np.float64))
    if sim.shape != ref.shape:
        raise ParameterError(f"simulated curves have shape {sim.shape}, reference {ref.shape}")
    if not (np.all(np.isfinite(sim)) and np.all(np.isfinite(ref))):
        raise ParameterError("force curves contain NaN/inf values")
    return sim, ref


def point_costs(sim: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """(P,) float64: ``G_j = sum_i (F_ref - F_sim)^2`` per point [N^2]; inputs (P, S) [N]."""
    sim, ref = _pair(sim, ref)
    return np.sum((ref - sim) ** 2, axis=1)


def relative_rms_error(sim: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """(P,) float64: ``RMS(F_sim - F_ref) / max|F_ref|`` per point [1]; inputs (P, S) [N].

    A reference curve that is identically zero has no scale to compare against
    and raises :class:`ParameterError` rather than returning inf/NaN.
    """
    sim, ref = _pair(sim, ref)
    scale = np.max(np.abs(ref), axis=1)
    if np.any(scale == 0.0):
        bad = np.nonzero(scale == 0.0)[0]
        raise ParameterError(f"reference curves of points {bad.tolist()} are identically zero")
    return np.sqrt(np.mean((sim - ref) ** 2, axis=1)) / scale
