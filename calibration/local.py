"""Local tuning: per-point ring offsets fitted by Jacobi sweeps of small least-squares problems.

Method:

* each calibration point j owns offsets ``z_j`` for the connectors of its ring
  (those the indenter loads directly: incident to j for the vertex indenter,
  leaving the footprint for a punch; :func:`calibration.parametrisation.build_rings`),
  within a factor :data:`~calibration.parametrisation.MAX_LOCAL_FACTOR` of the
  global values, in the coordinates of
  :mod:`calibration.parametrisation`: static ``(log s_K0, s dalpha, s^2 dbeta)``
  fitted on j's static curve, then relaxation ``(log s_k1, log s_tau1, log s_k2,
  log s_tau2)`` fitted on j's relaxation curve with the static offsets fixed; a
  connector in two rings gets the mean offset (geometric mean of the factors);
* a **Jacobi sweep** fits every point with the other points' offsets frozen at
  the sweep's start (3-D / 4-D least squares on that point's own curve, run on the
  worker that owns the point), then applies all new offsets at once, scaled by the
  fraction 1, 1/2, ..., 1/2^:data:`MAX_HALVINGS` (in the offset coordinates, i.e. in
  log space for the factors) that gives the lowest total cost over the calibration
  points, halving while the cost keeps dropping (a backtracking line search on the
  Jacobi step: a punch's rings share many connectors, and the full step of points that
  each fit their own curve exactly overshoots; on the punch scene with the volume term
  this took the calibration points from 1.51 / 1.99 % to 0.43 / 0.69 %). If no fraction
  lowers the total cost, the phase stops at the sweep's start. The result does not
  depend on the order of the points by construction;
* sweeps repeat until one lowers the total cost by less than
  ``calibration.local_sweep_tolerance`` times the total cost at the phase's
  start, or less than that is left to gain, or ``local_max_sweeps`` is reached;
  likewise each point's ``fatol`` is relative to its cost at the phase's start
  (later sweeps do not chase residues negligible against the misfit the phase
  began with). A checkpoint is written after every point's fit and every sweep.

Each point's fit is Levenberg-Marquardt with forward-difference Jacobians
(:func:`calibration.optimize.gauss_newton`), its steps cut to :data:`LOCAL_MAX_STEP` in
every offset coordinate at first (a trust radius that doubles while the steps it cuts
predict the cost well: with a fixed cut, two points of the coarse h = 0.025 m liver crawled
towards a far optimum and stopped at their budget, 3.2 % at the calibration points against
Nelder-Mead's 0.53 %; with the trust radius 0.55 %). Why not Nelder-Mead, the paper's
global fits' optimiser: on the default liver both reach the same offsets (calibration-point
errors 0.069 / 0.792 % against 0.071 / 0.793 %, held-out errors equal to 0.01 points), and
Gauss-Newton in a tenth of the evaluations (~20 per fit and sweep against ~100-300). Without the step cut, the first
full Gauss-Newton step of one point (vertex 232) jumped into another basin of its
non-convex static cost (4.3 % against 0.3 %). A fit whose trial step left the feasible
region (a spring tangent below its floor, an offset beyond its factor) ends with a
Nelder-Mead simplex from where Gauss-Newton stopped (:data:`BOUND_FINISH_STEP`): there the
optimum is on the boundary, Gauss-Newton's steps all point out of the region and its damped
steps crawl along it, while the simplex slides along it. On the bench's h = 0.0182 m mesh
with 8 calibration points, every point presses against the floor, and Gauss-Newton alone
fitted them to 3.25 / 2.61 % (Nelder-Mead 1.47 / 2.44 %); with the finish 0.85 / 2.26 %.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from typing import Callable

import numpy as np

from calibration.optimize import INFEASIBLE, Fit, gauss_newton
from calibration.parametrisation import (GlobalParams, Rings, StrainRange, check_feasible,
                                         check_offsets, check_spring_range, local_params)
from calibration.pool import Pool, PointWorker, forget_warm_starts
from calibration.progress import progress_bar
from forcecal.scene import CalibrationSection
from particle.params import ConnectorParams

log = logging.getLogger(__name__)

MAX_HALVINGS = 4  # an update damped to 1/16 that still raises the total cost ends the phase
# scale of every offset coordinate (a 22 % factor, or 0.2 s dalpha): its difference quotients
# step FD_STEP times this
LOCAL_STEP = 0.2
#: largest change of any offset coordinate in the first Gauss-Newton step (a factor
#: e^0.5 = 1.65, or 0.5 s dalpha): the fit stays in the basin it starts in (module docstring);
#: the radius doubles after each cut step the linear model predicted well
LOCAL_MAX_STEP = 0.5
#: a fit whose trial step left the feasible region ends with a Nelder-Mead simplex of this
#: size times LOCAL_STEP (:func:`calibration.optimize.gauss_newton`'s ``bound_finish``)
BOUND_FINISH_STEP = 0.5
PHASE_KIND = {"static": "indentation", "relaxation": "relaxation"}


@dataclass(frozen=True, eq=False)
class LocalParametrisation:
    """Global parameters + ring offsets -> connector parameters (picklable, sent to workers).

    Attributes:
        glob: the global parameter set.
        rings: first rings of the calibration points.
        strain: strain range of the experiments (feasibility and coordinate scale).
        floor: smallest feasible spring stiffness K(eps) on that range [N/m]
            (``calibration.stiffness_floor`` x the global K0, times ``shape`` if given: (E,)).
        z_static: (Pc, 3) static offsets.
        z_relaxation: (Pc, 4) relaxation offsets.
        validity: None, or per connector (low (E,), high (E,), floor (E,), ceiling (E,)): a
            strain range beyond the experiments' (the gravity release range of the FE sag) on
            which every spring's tangent must stay within [floor, ceiling] [N/m]
            (:func:`calibration.core.local_validity`).
        shape: the global fit's (E,) per-connector factors
            (:func:`calibration.parametrisation.global_shape`), None if uniform.
    """
    glob: GlobalParams
    rings: Rings
    strain: StrainRange
    floor: float | np.ndarray
    z_static: np.ndarray
    z_relaxation: np.ndarray
    validity: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None
    shape: np.ndarray | None = None

    def check(self, params: ConnectorParams) -> None:
        """Raise :class:`ParameterError` if ``params`` leave the searched region."""
        check_feasible(params, self.strain, self.floor)
        if self.validity is not None:
            low, high, floor, ceiling = self.validity
            check_spring_range(params, low, high, floor, "on its validity range", ceiling)

    def offsets(self, phase: str) -> np.ndarray:
        return self.z_static if phase == "static" else self.z_relaxation

    def with_offsets(self, phase: str, z: np.ndarray) -> "LocalParametrisation":
        key = "z_static" if phase == "static" else "z_relaxation"
        return dataclasses.replace(self, **{key: np.asarray(z, dtype=float)})

    def scaled(self, fraction: float) -> "LocalParametrisation":
        """Every offset times ``fraction`` (0: the global fit; the factors' logs scale)."""
        return dataclasses.replace(self, z_static=fraction * self.z_static,
                                   z_relaxation=fraction * self.z_relaxation)

    def params(self) -> ConnectorParams:
        return local_params(self.glob, self.rings, self.strain, self.z_static, self.z_relaxation,
                            self.shape)


@dataclass(frozen=True, eq=False)
class Sweep:
    """One Jacobi sweep of a local phase.

    Attributes:
        start_cost: total cost over the calibration points at the sweep's start [N^2].
        end_cost: total cost after the (damped) update, or the start cost if rejected [N^2].
        halvings: times the update was halved (-1 if it was rejected).
        fits: the per-point fits, in calibration-point order.
    """
    start_cost: float
    end_cost: float
    halvings: int
    fits: tuple[Fit, ...]

    @property
    def accepted(self) -> bool:
        return self.halvings >= 0


def fit_point(worker: PointWorker, local: LocalParametrisation, phase: str, point: int,
              reference: np.ndarray, settings: CalibrationSection, scale: float | None,
              verbose: bool) -> Fit:
    """Call run on the worker owning ``point``: fit its offsets, the others' frozen (Jacobi).

    ``scale`` is the point's cost at the start of the phase (None in the first
    sweep, where it is the fit's own start): ``fatol`` is relative to it.
    """
    kind = PHASE_KIND[phase]
    z = local.offsets(phase)
    node = int(worker.experiments.problem.test_points[point])
    # each fit is checkpointed: start cold, as a resumed run does (identical resumes)
    forget_warm_starts(worker)

    def residuals(zj: np.ndarray) -> np.ndarray:
        check_offsets(phase, zj)
        trial = z.copy()
        trial[point] = zj
        params = local.with_offsets(phase, trial).params()
        local.check(params)
        return reference - worker.curves(kind, params, [point])[0]

    return gauss_newton(residuals, z[point], np.full(z.shape[1], LOCAL_STEP),
                        name=f"local {phase} fit of point {point} (vertex {node})",
                        xatol=settings.xatol, fatol=settings.fatol, scale=scale,
                        max_step=LOCAL_MAX_STEP, bound_finish=BOUND_FINISH_STEP,
                        max_evaluations=settings.local_max_evaluations,
                        verbose=verbose)


def run_local_phase(pool: Pool, local: LocalParametrisation, phase: str, reference: np.ndarray,
                    settings: CalibrationSection, saved: dict | None,
                    save: Callable[[dict], None], *, progress: bool = True,
                    verbose: bool = False) -> tuple[LocalParametrisation, list[Sweep]]:
    """Jacobi sweeps of one phase (module docstring).

    Args:
        pool: evaluation pool (calibration points are test points 0..Pc-1).
        local: the starting parametrisation; its offsets of ``phase`` are the sweeps' start.
        phase: "static" or "relaxation".
        reference: (Pc, S) reference curves of the calibration points [N].
        saved: this phase's checkpoint record (None for a fresh start).
        save: stores the phase's record in the checkpoint.
    """
    kind = PHASE_KIND[phase]
    n_points = local.rings.n_points
    points = np.arange(n_points)
    record = saved or {"sweeps": []}
    sweeps: list[Sweep] = []
    for k in range(settings.local_max_sweeps):
        if k < len(record["sweeps"]):
            entry = record["sweeps"][k]
        else:
            if not sweeps:
                pool.forget_warm_starts()  # as after a resume (identical resumes)
            start_cost = (sweeps[-1].end_cost if sweeps else
                          pool.total_cost(kind, local.params(), points, reference))
            entry = {"start": local.offsets(phase).tolist(), "start_cost": start_cost,
                     "fits": {}}
            record["sweeps"].append(entry)
            save(record)
        start = local.with_offsets(phase, entry["start"])
        fits = _sweep_fits(pool, start, phase, reference, settings, _point_scales(record, k),
                           entry, record, save, f"local {phase} sweep {k + 1}", progress, verbose)
        if "end" not in entry:
            pool.forget_warm_starts()  # the fits before may have been loaded (resume)
            entry.update(_damped_update(pool, start, phase, reference, fits, entry["start_cost"]))
            save(record)
        sweep = Sweep(entry["start_cost"], entry["end_cost"], entry["halvings"], tuple(fits))
        sweeps.append(sweep)
        local = start.with_offsets(phase, entry["end"])
        # stop when this sweep gained, or the next could gain (at most what is left),
        # less than the tolerance times the phase's starting cost
        tolerance = settings.local_sweep_tolerance * record["sweeps"][0]["start_cost"]
        log.info("local %s sweep %d: total cost %.6g -> %.6g (%s)", phase, k + 1,
                 sweep.start_cost, sweep.end_cost,
                 f"update halved {sweep.halvings} times" if sweep.accepted else "rejected")
        if (not sweep.accepted or sweep.start_cost - sweep.end_cost < tolerance
                or sweep.end_cost < tolerance):
            break
    return local, sweeps


def _point_scales(record: dict, k: int) -> list[float | None]:
    """Per point the fatol scale of sweep ``k`` of a phase record: its cost at the phase's
    start (None in the first sweep: the fit's own start)."""
    first = record["sweeps"][0]
    if k == 0:
        return [None] * len(first["start"])
    return [first["fits"][str(j)]["initial_cost"] for j in range(len(first["start"]))]


def _sweep_fits(pool: Pool, start: LocalParametrisation, phase: str, reference: np.ndarray,
                settings: CalibrationSection, scales: list[float | None], entry: dict,
                record: dict, save: Callable[[dict], None], desc: str, progress: bool,
                verbose: bool) -> list[Fit]:
    """Fit every point not yet in ``entry["fits"]``, checkpointing after each one."""
    n_points = start.rings.n_points
    todo = [j for j in range(n_points) if str(j) not in entry["fits"]]
    with progress_bar(desc, n_points, progress, initial=n_points - len(todo)) as bar:
        calls = [(j, (start, phase, j, reference[j], settings, scales[j], verbose))
                 for j in todo]
        for i, fit in pool.map(fit_point, calls):
            entry["fits"][str(todo[i])] = fit.as_dict()
            save(record)
            bar.update(1)
            bar.set_postfix_str(f"point {todo[i]}: {fit.initial_cost:.3g} -> {fit.cost:.3g}")
    return [Fit.from_dict(entry["fits"][str(j)]) for j in range(n_points)]


def _damped_update(pool: Pool, start: LocalParametrisation, phase: str, reference: np.ndarray,
                   fits: list[Fit], start_cost: float) -> dict:
    """Apply all points' new offsets at once, the step halved while that lowers the total cost
    (the first fraction that lowers it below ``start_cost``, then halving on while it keeps
    dropping; module docstring)."""
    kind = PHASE_KIND[phase]
    z0 = start.offsets(phase)
    step = np.array([f.x for f in fits]) - z0
    points = np.arange(len(fits))
    best = None
    for halvings in range(MAX_HALVINGS + 1):
        z = z0 + step / 2 ** halvings
        params = start.with_offsets(phase, z).params()
        try:
            start.check(params)
            cost = pool.total_cost(kind, params, points, reference)
        except INFEASIBLE as exc:  # e.g. a blend of feasible rings that is not: damp further
            log.info("local %s update x 1/%d is infeasible: %s", phase, 2 ** halvings, exc)
            if best is not None:
                break
            continue
        if best is not None and cost >= best["end_cost"]:
            break  # halving further stopped lowering the cost
        if cost < start_cost:
            best = {"end": z.tolist(), "end_cost": cost, "halvings": halvings}
    if best is not None:
        return best
    log.info("local %s sweep: no damped update lowers the total cost; keeping the sweep's start",
             phase)
    return {"end": z0.tolist(), "end_cost": start_cost, "halvings": -1}

