"""Error measures between simulated and reference force curves.

Two numbers, defined once for the whole project:

* the paper's cost ``G_j = sum_i (F_ref,i - F_sim,i)^2`` of test point j over its
  curve samples [N^2] (what the optimisers minimise, summed over calibration points);
* the relative RMS error ``RMS(F_sim - F_ref) / max|F_ref|`` of each point [1]
  (what every report quotes), of the normal force; and its twin for the whole force
  vector, and for the vector's tangential part, on the same scale (the normal curve's
  largest magnitude), which ``report.json`` quotes as ``force_vector_errors``.
"""

from __future__ import annotations

import numpy as np

from forcecal.errors import ParameterError
from particle.evaluators import normal_force


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
    return np.sqrt(np.mean((sim - ref) ** 2, axis=1)) / _curve_scale(ref)


def _curve_scale(curves: np.ndarray) -> np.ndarray:
    """(P,) ``max|F|`` of each (P, S) reference curve [N], the relative errors' denominator;
    :class:`ParameterError` for a curve that is identically zero (no scale to compare
    against)."""
    scale = np.max(np.abs(curves), axis=1)
    if np.any(scale == 0.0):
        bad = np.nonzero(scale == 0.0)[0]
        raise ParameterError(f"reference curves of points {bad.tolist()} are identically zero")
    return scale


def force_vector_errors(sim: np.ndarray, ref: np.ndarray, normals: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray]:
    """((P,), (P,)) float64 relative RMS errors of the whole force vector and of its
    tangential part per point [1]: ``RMS_i |F_sim - F_ref| / max_i |F_ref . n|`` and the same
    with the difference's normal component removed; inputs (P, S, 3) force vectors [N] and
    (P, 3) unit normals.

    The scale is the normal curve's, as for :func:`relative_rms_error`, so the vector error
    is never below the normal one and the three compare directly (a tangential reaction
    peaks near zero load, where a relative measure of its own has no scale). A point whose
    normal curve is identically zero raises :class:`ParameterError`.
    """
    if np.ndim(sim) != 3 or np.ndim(ref) != 3 or np.shape(sim)[2] != 3 or np.shape(ref)[2] != 3:
        raise ParameterError(f"simulated force vectors have shape {np.shape(sim)}, reference "
                             f"{np.shape(ref)}; both must be (P, S, 3)")
    sim, ref = _pair(sim, ref)
    normals = np.asarray(normals, dtype=np.float64)
    if normals.shape != (len(ref), 3):
        raise ParameterError(f"{len(ref)} points but normals of shape {normals.shape}")
    scale = _curve_scale(normal_force(ref, normals))
    diff = sim - ref
    tangential = diff - normal_force(diff, normals)[:, :, None] * normals[:, None, :]

    def rms(d: np.ndarray) -> np.ndarray:
        return np.sqrt(np.mean(np.sum(d ** 2, axis=2), axis=1)) / scale

    return rms(diff), rms(tangential)
