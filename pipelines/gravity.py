"""Gravity test, particle side: static sag and dynamic release -> ``gravity.h5``.

The calibrated model and the closed-form baseline are run through the same
experiments as the FE reference (``reference.h5:/gravity``): base nodes fixed,
gravity ``scene.gravity.acceleration``; the static sag uses the long-term model
(springs only, arms relaxed), the dynamic run releases the organ from rest in
its undeformed shape at t = 0 with the Maxwell arms active and is sampled at
exactly the FE's record times, so the comparison needs no interpolation.

A model that does not complete its test (no static equilibrium at full load, a release that
leaves its verified strain range, a spring whose stiffness reaches zero) is a result, not a
crash: its failure is recorded (:class:`calibration.validation.ValidationFailure`, by the
function the calibration's gravity check runs too,
:func:`calibration.gravity_check.gravity_outcome`) and the other model's results are kept.

``gravity.h5`` (kind ``forcecal.gravity``, schema 1; every dataset has a
``unit`` attribute):

| path | shape | unit | content |
|---|---|---|---|
| ``/`` attrs | | | ``kind``, ``schema_version``, ``forcecal_version``, ``created``, ``acceleration`` (3,) m/s^2, ``reference_fingerprint`` (SHA-256 of the reference's gravity content, :func:`forcecal.h5io.reference_digest`), ``params_fingerprint`` (SHA-256 of the file), ``experiments`` (JSON list of the gravity experiments run; absent = both), ``failures`` (JSON list of the models' failures, records as in ``params.h5`` with ``experiment`` ``gravity_static`` (``reached``: ``{"load_factor": ...}``, the fraction of the gravity carried) or ``gravity_dynamic`` (``{"time_s": ...}``), ``point`` and ``role`` null; absent in files written before it: none) |
| ``/mesh``, ``/test_points`` | | | as in ``reference.h5`` |
| ``/time`` | (S,) | s | sample times of the dynamic run (the FE's), from rest at 0 (only with ``gravity_dynamic``, like ``displacement``) |
| ``/<model>/static_displacement`` | (N, 3) | m | static sag of every vertex |
| ``/<model>/displacement`` | (S, N, 3) | m | dynamic vertex displacements |
| ``/<model>`` attrs | | | ``dt`` [s] explicit step used, ``critical_dt`` [s] its stability limit, ``static_time``, ``dynamic_time`` [s] wall times, ``strain_min``, ``strain_max`` [1] connector strain extremes over both runs |

| ``/second_support`` | | | the same test with the second support's clamp (experiment ``second_support``, held out like the gravity test): attrs ``tracked_node``; datasets ``fixed`` (F2,) its clamped vertices, ``time`` (S,) s, and a ``<model>`` group as above for each model; failures recorded with ``experiment`` ``second_support_static`` / ``second_support_dynamic`` |

``<model>`` is ``calibrated`` (global + local tuning, or the gradient fit) and ``baseline``
(Van Gelder). A model whose static sag failed has no group; one whose release failed has no
``displacement`` (and ``dynamic_time`` 0): each only with its failure recorded.
The static sag is always computed (the release's time step is chosen from its
strains); the dynamic release only when the scene's experiments include
``gravity_dynamic`` (otherwise ``dynamic_time`` is 0).
"""

from __future__ import annotations

import dataclasses
import json
import logging
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from calibration.gravity_check import gravity_outcome
from calibration.validation import ValidationFailure, failures_json, parse_failures
from forcecal.errors import DataFileError
from forcecal.h5io import (Reference, atomic_h5, attr, get, group, json_attr, open_h5, put,
                           read_problem, write_problem)
from forcecal.problem import Problem
from forcecal.scene import (GRAVITY_EXPERIMENTS, HELD_OUT_EXPERIMENTS, SECOND_SUPPORT_PARTS,
                            Scene)
from particle.experiments import GravityTest
from particle.params import ConnectorParams

log = logging.getLogger(__name__)

GRAVITY_KIND = "forcecal.gravity"
GRAVITY_SCHEMA = 1
MODELS = ("calibrated", "baseline")
SCALARS = ("dt", "critical_dt", "static_time", "dynamic_time", "strain_min", "strain_max")


@dataclass(frozen=True, eq=False)
class SupportRuns:
    """The models' runs of the second support's test (``/second_support`` of ``gravity.h5``).

    Attributes:
        fixed: (F2,) int64, the vertices it clamps (the reference's).
        tracked_node: the vertex whose release is compared.
        time: (S,) float64, sample times [s] (the FE's).
        models: model name -> its runs, as :attr:`GravityRuns.models`.
    """
    fixed: np.ndarray
    tracked_node: int
    time: np.ndarray
    models: dict[str, GravityTest]


@dataclass(frozen=True, eq=False)
class GravityRuns:
    """Everything in ``gravity.h5``.

    Attributes:
        problem: mesh, fixed nodes, test points, tracked node.
        time: (S,) float64, sample times [s].
        acceleration: (3,) float64, gravitational acceleration [m/s^2].
        models: model name (:data:`MODELS`) -> its runs (a model whose static sag failed
            is absent; one whose release failed has no ``displacement``).
        reference_fingerprint, params_fingerprint: SHA-256 of the input files.
        experiments: the gravity experiments run (``time`` is None without
            ``gravity_dynamic``), and ``second_support`` when it ran.
        failures: what the models failed (their ``experiment`` says which run).
        second_support: the second support's runs (None when not run).
    """
    problem: Problem
    time: np.ndarray | None
    acceleration: np.ndarray
    models: dict[str, GravityTest]
    reference_fingerprint: str = ""
    params_fingerprint: str = ""
    experiments: tuple[str, ...] = GRAVITY_EXPERIMENTS
    failures: tuple[ValidationFailure, ...] = ()
    second_support: SupportRuns | None = None


def run_gravity(scene: Scene, reference: Reference, connectors: dict[str, ConnectorParams],
                strain_range: tuple[float, float], *, reference_fingerprint: str = "",
                params_fingerprint: str = "") -> GravityRuns:
    """Run every model of :data:`MODELS` through the reference's gravity experiments
    (:func:`calibration.gravity_check.gravity_outcome`: the static sag and the release, whose
    explicit step is chosen for each connector's strain range of the release and verified)
    and, with ``second_support``, through the same test with the second support's clamp
    (``reference.h5:/second_support``).

    ``strain_range`` is the calibration's: where the calibrated springs are valid. A model
    that fails is recorded in ``failures`` and the others run on.
    """
    experiments = tuple(e for e in HELD_OUT_EXPERIMENTS if scene.runs(e))
    for e in experiments:
        reference.require(e)
    g = np.asarray(scene.gravity.acceleration, dtype=np.float64)
    times = reference.gravity.time if "gravity_dynamic" in experiments else None
    missing = [m for m in MODELS if m not in connectors]
    if missing:
        raise DataFileError(f"params.h5 lacks connector parameters {missing}")
    failures: list[ValidationFailure] = []
    models = (_model_runs(scene, reference.problem, connectors, times, strain_range, failures)
              if "gravity_static" in experiments else {})
    second = None
    if "second_support" in experiments:
        ref = reference.second_support
        clamped = dataclasses.replace(reference.problem, fixed=ref.fixed)
        second = SupportRuns(ref.fixed, ref.runs.tracked_node, ref.runs.time, _model_runs(
            scene, clamped, connectors, ref.runs.time, strain_range, failures,
            SECOND_SUPPORT_PARTS))
    return GravityRuns(reference.problem, times, g, models, reference_fingerprint,
                       params_fingerprint, experiments, tuple(failures), second)


def _model_runs(scene: Scene, problem: Problem, connectors: dict[str, ConnectorParams],
                times: np.ndarray | None, strain_range: tuple[float, float],
                failures: list[ValidationFailure],
                parts: tuple[str, str] = GRAVITY_EXPERIMENTS) -> dict[str, GravityTest]:
    """Every model's :func:`~calibration.gravity_check.gravity_outcome` with ``problem``'s
    clamp, the runs that completed (their failures appended to ``failures``)."""
    models = {}
    for m in MODELS:
        run, failure = gravity_outcome(scene, problem, connectors[m], times, strain_range, m,
                                       parts)
        if run is not None:
            models[m] = run
        if failure is not None:
            log.warning("%s: %s", parts[0].rsplit("_", 1)[0].replace("_", " "),
                        failure.describe())
            failures.append(failure)
    return models


def write_gravity(path: str | Path, runs: GravityRuns) -> None:
    """Write ``gravity.h5`` atomically (schema in the module docstring)."""
    with atomic_h5(path, GRAVITY_KIND, GRAVITY_SCHEMA) as fh:
        fh.attrs["acceleration"] = runs.acceleration
        fh.attrs["reference_fingerprint"] = runs.reference_fingerprint
        fh.attrs["params_fingerprint"] = runs.params_fingerprint
        fh.attrs["experiments"] = json.dumps(list(runs.experiments))
        fh.attrs["failures"] = failures_json(runs.failures)
        write_problem(fh, runs.problem)
        if runs.time is not None:
            put(fh, "time", runs.time, "s", "sample times of the dynamic run (S,)")
        _write_models(fh, runs.models)
        second = runs.second_support
        if second is not None:
            g = fh.create_group("second_support")
            g.attrs["tracked_node"] = second.tracked_node
            put(g, "fixed", second.fixed, "1", "vertices the second support clamps (F2,)")
            put(g, "time", second.time, "s", "sample times of its release (S,)")
            _write_models(g, second.models)


def _write_models(fh: h5py.Group, models: dict[str, GravityTest]) -> None:
    """One ``<model>`` group per run of ``models`` under ``fh``."""
    for name, r in models.items():
        g = fh.create_group(name)
        put(g, "static_displacement", r.static_displacement, "m", "static sag (N, 3)")
        if r.displacement is not None:
            put(g, "displacement", r.displacement, "m", "dynamic displacements (S, N, 3)")
        for k in SCALARS:
            g.attrs[k] = getattr(r, k)


def read_gravity(path: str | Path) -> GravityRuns:
    """Read ``gravity.h5`` back (kind, schema, shapes and finiteness checked; a model's
    missing run must be one its recorded failure explains)."""
    with open_h5(path, GRAVITY_KIND, GRAVITY_SCHEMA) as fh:
        problem = read_problem(fh)
        experiments = tuple(json_attr(fh, "experiments", GRAVITY_EXPERIMENTS))
        failures = parse_failures(json_attr(fh, "failures", []), f"{path}: failures")
        dynamic = "gravity_dynamic" in experiments
        times = get(fh, "time", (None,), dtype="float") if dynamic else None
        n = problem.mesh.n_vertices
        models = (_read_models(fh, "", times, n, failures)
                  if "gravity_static" in experiments else {})
        second = None
        if "second_support" in experiments:
            g = group(fh, "second_support")
            fixed = get(fh, "second_support/fixed", (None,), dtype="int")
            t = get(fh, "second_support/time", (None,), dtype="float")
            second = SupportRuns(fixed, int(attr(g, "tracked_node")), t, _read_models(
                fh, "second_support/", t, n, failures, SECOND_SUPPORT_PARTS))
        return GravityRuns(problem, times, np.asarray(attr(fh, "acceleration"), dtype=float),
                           models, str(attr(fh, "reference_fingerprint")),
                           str(attr(fh, "params_fingerprint")), experiments, failures, second)


def _read_models(fh: h5py.File, prefix: str, times: np.ndarray | None, n: int,
                 failures: tuple[ValidationFailure, ...],
                 parts: tuple[str, str] = GRAVITY_EXPERIMENTS) -> dict[str, GravityTest]:
    """The ``<prefix><model>`` groups (a model's missing run must be one its recorded failure
    of ``parts``, the test's static sag and release, explains)."""
    models = {}
    for name in MODELS:
        failed = {f.experiment for f in failures if f.model == name}
        path = f"{prefix}{name}"
        if path not in fh:
            if parts[0] not in failed:
                raise DataFileError(f"{fh.filename}:/{path} is missing")
            continue
        released = times is not None and parts[1] not in failed
        models[name] = GravityTest(
            get(fh, f"{path}/static_displacement", (n, 3), dtype="float"),
            get(fh, f"{path}/displacement", (len(times), n, 3), dtype="float")
            if released else None,
            *(float(attr(fh[path], k)) for k in SCALARS))
    return models
