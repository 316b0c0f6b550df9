"""Real-time verdict: the calibrated model's haptic cost on the scene's mesh at 1 kHz.

``report.json``'s ``realtime`` block says, before anyone uses the model, whether it runs at
haptic rate on this mesh: a :class:`~particle.haptics.HapticSession` of the calibrated model
(1 ms of simulated time per :meth:`~particle.haptics.HapticSession.step`, one thread, the
scene's step rule ``particle.dt`` / ``dt_safety``) drags a test point :data:`CALLS` times, as
the benchmark's drag does (:func:`pipelines.bench.particle_engine.haptic_drag`): the point is
pushed the scene's indentation depth along its inward normal over the first quarter of the
calls, then held. The session is verified on the haptic default strain range (+-0.5,
:data:`particle.stability.DEFAULT_STRAIN_RANGE`), cut short of where a calibrated spring would
lose its stiffness (as the gravity release is, :data:`~particle.stability.SOFT_SPRING_CLEARANCE`).

Keys: ``substeps_per_ms`` (explicit steps per 1 ms call), ``dt_s`` (the step) and
``critical_dt_s`` (its stability limit), ``step_min_us`` / ``step_median_us`` / ``step_p99_us`` /
``step_max_us`` (wall time per call) and ``step_cpu_us`` (the process CPU time per call, which
time spent waiting for a core does not count: on a busy machine the p99 measures the other
processes, the CPU time much less), ``calls``, ``tool_node`` and ``depth_m`` (the drag),
``load_average`` (1 min, before the drag: the timings depend on it), ``limiting_edges`` and
``limiting_tets`` (what sets the stable step, :func:`step_limiters`), ``edge_min_m`` (the
mesh's shortest edge),
``goal_us`` (the project's p99 goal per call), ``status`` (``measured``, or ``failed`` with
``reason`` and null timings when the drag cannot run: the session refused its step or a
connector left its verified range).

What sets the step: the stability limit is ``2/omega_max`` with ``omega_max^2`` bounded by the
bound the step is taken from (:func:`particle.stability.step_bound`, as
:func:`~particle.stability.critical_time_step` and so every session and integrator take it):
the largest eigenvalue ``lambda`` of the mass-scaled graph Laplacian of the connectors'
stiffness bounds, with the volume term either its edge weights added to them or its own bound
(the largest eigenvalue of its nonnegative scalar matrix ``S = sum_t S_t``, or a smaller
per-particle/element bound) added to ``lambda``, whichever is smaller. The Laplacian's top
eigenvector ``y`` gives ``lambda = sum_e kappa_e (x_i - x_j)^2`` with ``x = M^{-1/2} y`` (a
Rayleigh quotient), so each connector's term over ``lambda`` is its exact share of that mode;
likewise each tet's ``x^T S_t x`` at ``S``'s top eigenvector. A share is that part's fraction
of the whole bound (the Laplacian's and the volume term's parts weighted by what each adds), so
the connectors with the largest shares are those whose stiffness and light end particles
(short edges, small or flat tets) set the step. ``limiting_edges`` lists them (connector,
particles, rest length, share), ``limiting_tets`` the tets whose six edges carry the largest
shares plus, when the volume term's own bound is added, the tet's share of it.
"""

from __future__ import annotations

import logging
import os
from typing import Any

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import eigsh

from forcecal.errors import ParameterError, StabilityError
from forcecal.problem import Problem
from forcecal.scene import Scene
from particle.model import Model
from particle.params import ConnectorParams, connector_strain_bounds
from particle.stability import (DEFAULT_STRAIN_RANGE, DENSE_EIGEN_LIMIT, SOFT_SPRING_CLEARANCE,
                                critical_time_step, positive_spring_range, resolve_time_step,
                                step_bound)
from particle.volume_bounds import volume_tet_energies

log = logging.getLogger(__name__)

#: calls of the timed drag: 2 s of device time, enough for a p99 of 20 calls
CALLS = 2000
#: the device period [s]: 1 kHz
PERIOD = 1e-3
#: the project's goal for the p99 of one call [us] (docs/benchmarks.md)
GOAL_US = 100.0
#: connectors and tets listed as setting the step
LIMITERS = 5


def session_strain_range(params: ConnectorParams) -> tuple[np.ndarray, np.ndarray]:
    """(lo (E,), hi (E,)): the haptic default +-0.5 cut to :data:`SOFT_SPRING_CLEARANCE` of the
    way to the strain where each spring's K(eps) reaches 0."""
    soft_lo, soft_hi = positive_spring_range(params)
    lo, hi = DEFAULT_STRAIN_RANGE
    return (np.maximum(lo, SOFT_SPRING_CLEARANCE * soft_lo),
            np.minimum(hi, SOFT_SPRING_CLEARANCE * soft_hi))


def step_limiters(model: Model, strain_range: tuple[np.ndarray, np.ndarray],
                  count: int = LIMITERS) -> dict[str, Any]:
    """The connectors and tets that set ``model``'s stable step on ``strain_range`` (module
    docstring): ``limiting_edges`` and ``limiting_tets``, each the ``count`` largest shares
    of the fastest modes of the step's bound (:func:`particle.stability.step_bound`), and
    ``edge_min_m``."""
    bound = step_bound(model, strain_range)
    free = np.nonzero(~model.fixed)[0]
    x = np.zeros(model.n_particles)
    x[free] = _top_eigenvector(bound.laplacian) / np.sqrt(model.masses[free])
    i, j = model.edges[:, 0], model.edges[:, 1]
    energy = bound.kappa * (x[i] - x[j]) ** 2
    share = energy / energy.sum() * (bound.laplacian_part / bound.omega2)
    edges = np.argsort(-share)[:count]
    out = {"edge_min_m": float(model.rest_lengths.min()),
           "limiting_edges": [{"connector": int(e), "particles": model.edges[e].tolist(),
                               "rest_length_m": float(model.rest_lengths[e]),
                               "share": float(share[e])} for e in edges],
           "limiting_tets": []}
    if model.n_tets:
        tet_share = share[model.tet_connectors].sum(axis=1)
        if bound.volume_matrix is not None:  # the volume term's own bound, added separately
            lo, hi = connector_strain_bounds(strain_range, model.n_connectors, model.edges)
            tet_energy = volume_tet_energies(model, lo, hi,
                                             np.abs(_top_eigenvector(bound.volume_matrix)))
            tet_share += tet_energy / tet_energy.sum() * (bound.volume_part / bound.omega2)
        out["limiting_tets"] = [{"tet": int(t), "particles": model.tets[t].tolist(),
                                 "volume_m3": float(model.rest_volumes[t]),
                                 "share": float(tet_share[t])}
                                for t in np.argsort(-tet_share)[:count]]
    return out


def _top_eigenvector(matrix: sp.csr_matrix) -> np.ndarray:
    """Unit eigenvector of the largest eigenvalue of a symmetric sparse matrix (dense below
    :data:`~particle.stability.DENSE_EIGEN_LIMIT` rows, else Lanczos from a fixed start, as
    the stable step's eigenvalue is computed)."""
    n = matrix.shape[0]
    if n <= DENSE_EIGEN_LIMIT:
        return np.linalg.eigh(matrix.toarray())[1][:, -1]
    start = np.random.default_rng(0).uniform(0.5, 1.5, n)
    return eigsh(matrix, k=1, which="LA", tol=1e-8, v0=start)[1][:, 0]


def realtime_block(scene: Scene, problem: Problem, model: Model) -> dict[str, Any]:
    """``report.json``'s ``realtime`` block for the calibrated ``model`` of ``problem``'s mesh
    (module docstring; :func:`calibration.loading.calibrated_model` builds it)."""
    from pipelines.bench.particle_engine import haptic_drag

    strain_range = session_strain_range(model.params)
    # the tool: the first held-out point (never fitted), else the first test point
    k = len(problem.calibration) if len(problem.held_out) else 0
    tool, depth = int(problem.test_points[k]), float(scene.indentation.depth)
    out: dict[str, Any] = {
        "status": "measured", "reason": None, "calls": CALLS, "period_s": PERIOD,
        "tool_node": tool, "depth_m": depth, "substeps_per_ms": None, "dt_s": None,
        "critical_dt_s": None, "step_min_us": None, "step_median_us": None,
        "step_p99_us": None, "step_max_us": None, "step_cpu_us": None, "goal_us": GOAL_US,
        "load_average": os.getloadavg()[0],
        "strain_range": [float(strain_range[0].min()), float(strain_range[1].max())]}
    try:
        critical = critical_time_step(model, strain_range=strain_range)
        out.update(step_limiters(model, strain_range))
        dt = resolve_time_step(scene.particle, critical)
        drag = haptic_drag(model, tool, problem.normals[k], dt, calls=CALLS, depth=depth,
                           strain_range=strain_range)
    except (ParameterError, StabilityError) as exc:
        out.update(status="failed", reason=f"{type(exc).__name__}: {exc}")
        log.warning("real-time check: the calibrated model's haptic session failed: %s",
                    out["reason"])
        return out
    us = drag["latencies_us"]
    out.update(substeps_per_ms=int(drag["substeps"]), dt_s=float(drag["dt_s"]),
               critical_dt_s=float(critical), step_min_us=float(us.min()),
               step_median_us=float(np.median(us)), step_p99_us=float(np.percentile(us, 99)),
               step_max_us=float(us.max()), step_cpu_us=float(drag["cpu_us"]))
    log.info("real-time check: %d substep(s) per 1 ms call (step %.3g s, limit %.3g s), "
             "median %.1f us, p99 %.1f us, CPU %.1f us per call over %d calls (load %.1f)",
             out["substeps_per_ms"], out["dt_s"], critical, out["step_median_us"],
             out["step_p99_us"], out["step_cpu_us"], CALLS, out["load_average"])
    return out


def realtime_line(block: dict[str, Any] | None) -> str:
    """One line saying the ``realtime`` block: substeps, median and p99 per call, or why not."""
    if not block:
        return "real time: not measured"
    if block["status"] != "measured":
        return f"real time: the haptic session failed: {block['reason']}"
    verdict = "within" if block["step_p99_us"] <= block["goal_us"] else "above"
    return (f"real time (1 kHz): {block['substeps_per_ms']} substep(s) per 1 ms call, median "
            f"{block['step_median_us']:.0f} us, p99 {block['step_p99_us']:.0f} us, CPU "
            f"{block['step_cpu_us']:.0f} us per call (p99 {verdict} the "
            f"{block['goal_us']:.0f} us goal; load {block['load_average']:.1f})")
