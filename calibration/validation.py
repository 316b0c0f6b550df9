"""Validation of the particle models: a model that fails an experiment is a result, not a crash.

The calibration evaluates three particle models at every test point (the closed-form
baseline, the global fit, the calibrated fit) and the gravity stage runs the calibrated
model and the baseline through the gravity test. A model that cannot complete one of these
experiments -- Newton finds no equilibrium beyond some depth or load, a spring's stiffness
K(eps) reaches zero, an explicit release leaves the strain range its step was verified for --
has not crashed the run: it has failed a check. Its failure is recorded as a
:class:`ValidationFailure` (the model, the experiment, the test point and its role, how far it
got and why), the experiment's result for that point is left out (NaN rows in ``params.h5``'s
curves, no dataset in ``gravity.h5``), and the run goes on to its report, whose verdict then
says which checks failed. Errors of the inputs (scene, mesh, data files) and of the FE
reference are not validation failures: they stay refusals.

What counts as a model's failure is :data:`MODEL_FAILURES`, raised by the particle code with
the load parameter reached (``ForcecalError.reached``: depth, time or load fraction).
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np

from calibration.pool import Pool, PointWorker, in_point_order
from forcecal.errors import (ConvergenceError, DataFileError, ForcecalError, ParameterError,
                             StabilityError)
from forcecal.problem import Problem
from particle.params import ConnectorParams

log = logging.getLogger(__name__)

#: what a particle model that cannot complete an experiment raises (each names the load, step,
#: connector or tet; :attr:`~forcecal.errors.ForcecalError.reached` says how far it got)
MODEL_FAILURES = (ConvergenceError, StabilityError, ParameterError)
#: the particle models validated
MODELS = ("global", "calibrated", "baseline")
#: experiment -> the key (and unit) of the load parameter a failure reached
REACHED_KEYS = {"indentation": "depth_m", "relaxation": "time_s",
                "gravity_static": "load_factor", "gravity_dynamic": "time_s"}
ROLES = ("calibration", "held_out")


@dataclass(frozen=True)
class ValidationFailure:
    """One particle model's failure to complete one validation experiment.

    Attributes:
        model: ``global``, ``calibrated`` or ``baseline`` (:data:`MODELS`).
        experiment: ``indentation``, ``relaxation``, ``gravity_static`` or
            ``gravity_dynamic`` (:data:`REACHED_KEYS`).
        point: the test point's vertex id (the particle indented); None for gravity.
        role: ``calibration`` or ``held_out`` for a test point, None for gravity.
        reached: how far the model got, in the experiment's load parameter
            (:data:`REACHED_KEYS`): the indentation depth [m], the time [s] of the
            relaxation or the release, the fraction of the gravity load carried [1].
        reason: the error's type and message.
    """
    model: str
    experiment: str
    point: int | None
    role: str | None
    reached: float
    reason: str

    def as_dict(self) -> dict[str, Any]:
        """The record of ``report.json``'s ``failures`` (and of the HDF5 files)."""
        return {"model": self.model, "experiment": self.experiment, "point": self.point,
                "role": self.role, "reached": {REACHED_KEYS[self.experiment]: self.reached},
                "reason": self.reason}

    @classmethod
    def from_dict(cls, record: Any, where: str) -> "ValidationFailure":
        """The failure of an :meth:`as_dict` record; DataFileError naming ``where`` if it is
        not one."""
        try:
            experiment = record["experiment"]
            failure = cls(str(record["model"]), str(experiment),
                          None if record["point"] is None else int(record["point"]),
                          record["role"], float(record["reached"][REACHED_KEYS[experiment]]),
                          str(record["reason"]))
        except (TypeError, KeyError, ValueError) as exc:
            raise DataFileError(f"{where}: {record!r:.120} is not a validation failure record "
                                f"({type(exc).__name__}: {exc})") from None
        if failure.model not in MODELS or failure.role not in (*ROLES, None):
            raise DataFileError(f"{where}: {record!r:.120} names an unknown model or role")
        return failure

    def describe(self) -> str:
        """One line: which model failed what, where, how far it got and why."""
        where = ("" if self.point is None
                 else f" at {self.role.replace('_', '-')} point {self.point}")
        unit = REACHED_KEYS[self.experiment].rsplit("_", 1)[-1]
        reached = (f"{1e3 * self.reached:.4g} mm" if unit == "m" else
                   f"{self.reached:.4g} s" if unit == "s" else f"{self.reached:.4g} g")
        return (f"the {self.model} model did not complete {self.experiment}{where} (reached "
                f"{reached}): {self.reason}")


def failure_from(exc: ForcecalError, model: str, experiment: str, point: int | None = None,
                 role: str | None = None) -> ValidationFailure:
    """The record of ``exc``, a :data:`MODEL_FAILURES` error of ``model`` in ``experiment``
    (a failure that does not say how far it got reached nothing: 0)."""
    reached = 0.0 if exc.reached is None else float(exc.reached)
    return ValidationFailure(model, experiment, point, role, reached,
                             f"{type(exc).__name__}: {exc}")


def failures_json(failures: Sequence[ValidationFailure]) -> str:
    """``failures`` as the JSON text the HDF5 files store (attribute ``failures``)."""
    return json.dumps([f.as_dict() for f in failures])


def parse_failures(records: Any, where: str) -> tuple[ValidationFailure, ...]:
    """The failures of a decoded ``failures`` attribute (a list of :meth:`as_dict` records)."""
    if not isinstance(records, list):
        raise DataFileError(f"{where}: failures = {records!r:.80} is not a list of records")
    return tuple(ValidationFailure.from_dict(r, where) for r in records)


def check_failed_rows(values: np.ndarray, failed: Sequence[int], where: str) -> np.ndarray:
    """``values`` (P, ...) read with its non-finite entries allowed: DataFileError unless the
    rows holding them are exactly the rows ``failed`` (test point indices whose model
    recorded a failure), which must be all NaN."""
    rows = np.zeros(len(values), dtype=bool)
    rows[list(failed)] = True
    finite = np.isfinite(values.reshape(len(values), -1))
    if not (np.all(finite[~rows]) and not np.any(finite[rows])):
        raise DataFileError(f"{where} has non-finite values at points without a recorded "
                            "validation failure, or finite values at a failed one")
    return values


def completed(values: np.ndarray) -> np.ndarray:
    """(P,) bool: the rows of (P, ...) ``values`` that are finite (the points a model
    completed; a failed point's rows are NaN)."""
    return np.all(np.isfinite(values.reshape(len(values), -1)), axis=1)


def per_completed_point(error: Callable[..., Any], sim: np.ndarray, ref: np.ndarray,
                        *per_point: np.ndarray) -> Any:
    """``error(sim, ref, *per_point)`` of the points ``sim`` completed (:func:`completed`),
    each (P,) result scattered back with NaN at the failed points (a tuple of results
    stays a tuple)."""
    rows = completed(sim)
    out = error(sim[rows], ref[rows], *(a[rows] for a in per_point))

    def scatter(values: np.ndarray) -> np.ndarray:
        full = np.full(len(sim), np.nan)
        full[rows] = values
        return full

    return tuple(scatter(v) for v in out) if isinstance(out, tuple) else scatter(out)


def point_validation(worker: PointWorker, kind: str, params: ConnectorParams,
                     points: Sequence[int]) -> tuple[np.ndarray, np.ndarray | None,
                                                     np.ndarray | None, list]:
    """Call run on a worker: the curves and force vectors of owned ``points`` (as
    :meth:`PointWorker.curves_and_forces`), each point on its own so that one that fails
    leaves NaN rows and the others their curves, and the connector strains each curve
    reached (:meth:`PointWorker.strain_extremes`). Returns (curves (P', S), forces (P', S, 3)
    or None, strains (P', 2) or None, [(test point index, error)] of the failed points)."""
    experiments = worker.experiments
    n = len(experiments.depths if kind == "indentation" else experiments.times)
    curves, forces = np.full((len(points), n), np.nan), np.full((len(points), n, 3), np.nan)
    strains = np.full((len(points), 2), np.nan)
    with_forces, with_strains, failed = True, True, []
    for i, point in enumerate(points):
        try:
            c, f = worker.curves_and_forces(kind, params, [point])
        except MODEL_FAILURES as exc:
            failed.append((int(point), exc))
            continue
        curves[i] = c[0]
        if f is None:
            with_forces = False
        else:
            forces[i] = f[0]
        reached = worker.strain_extremes(kind, [point])
        if reached is None:
            with_strains = False
        else:
            strains[i] = reached[0]
    return (curves, forces if with_forces else None, strains if with_strains else None,
            failed)


@dataclass(frozen=True, eq=False)
class Validated:
    """One model's results in one experiment at every test point (NaN rows where it failed).

    Attributes:
        curves: (P, S) normal-force curves [N].
        forces: (P, S, 3) force vectors [N], or None (the backend gives none).
        strains: (P, 2) the smallest and largest connector strain [1] each curve reached, or
            None (the backend gives none).
        failures: the points the model failed.
    """
    curves: np.ndarray
    forces: np.ndarray | None
    strains: np.ndarray | None
    failures: list[ValidationFailure]


def validate_points(pool: Pool, problem: Problem, model: str, params: ConnectorParams,
                    experiment: str) -> Validated:
    """``model`` (``params``) at every test point of ``problem`` in ``experiment``
    (:class:`Validated`)."""
    points = np.arange(len(problem.test_points))
    out, positions = pool.by_owner(point_validation, points, experiment, params)

    def gathered(i: int) -> np.ndarray | None:
        parts = [o[i] for o in out]
        return None if any(p is None for p in parts) else in_point_order(parts, positions)

    n_cal = len(problem.calibration)
    failed = sorted((f for *_, worker_failed in out for f in worker_failed),
                    key=lambda f: f[0])
    failures = [failure_from(exc, model, experiment, int(problem.test_points[k]),
                             ROLES[0] if k < n_cal else ROLES[1]) for k, exc in failed]
    for failure in failures:
        log.warning("validation: %s", failure.describe())
    return Validated(gathered(0), gathered(1), gathered(2), failures)
