"""Gravity test, particle side: static sag and dynamic release -> ``gravity.h5``.

The calibrated model and the closed-form baseline are run through the same
experiments as the FE reference (``reference.h5:/gravity``): base nodes fixed,
gravity ``scene.gravity.acceleration``; the static sag uses the long-term model
(springs only, arms relaxed), the dynamic run releases the organ from rest in
its undeformed shape at t = 0 with the Maxwell arms active and is sampled at
exactly the FE's record times, so the comparison needs no interpolation.

``gravity.h5`` (kind ``forcecal.gravity``, schema 1; every dataset has a
``unit`` attribute):

| path | shape | unit | content |
|---|---|---|---|
| ``/`` attrs | | | ``kind``, ``schema_version``, ``forcecal_version``, ``created``, ``acceleration`` (3,) m/s^2, ``reference_fingerprint`` (SHA-256 of the reference's gravity content, :func:`forcecal.h5io.reference_digest`), ``params_fingerprint`` (SHA-256 of the file), ``experiments`` (JSON list of the gravity experiments run; absent = both) |
| ``/mesh``, ``/test_points`` | | | as in ``reference.h5`` |
| ``/time`` | (S,) | s | sample times of the dynamic run (the FE's), from rest at 0 (only with ``gravity_dynamic``, like ``displacement``) |
| ``/<model>/static_displacement`` | (N, 3) | m | static sag of every vertex |
| ``/<model>/displacement`` | (S, N, 3) | m | dynamic vertex displacements |
| ``/<model>`` attrs | | | ``dt`` [s] explicit step used, ``critical_dt`` [s] its stability limit, ``static_time``, ``dynamic_time`` [s] wall times, ``strain_min``, ``strain_max`` [1] connector strain extremes over both runs |

``<model>`` is ``calibrated`` (global + local tuning, or the gradient fit) and ``baseline``
(Van Gelder).
The static sag is always computed (the release's time step is chosen from its
strains); the dynamic release only when the scene's experiments include
``gravity_dynamic`` (otherwise ``dynamic_time`` is 0).
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from forcecal.errors import DataFileError
from forcecal.h5io import Reference, atomic_h5, get, open_h5, put, read_problem, write_problem
from forcecal.problem import Problem
from forcecal.scene import Scene
from particle.experiments import gravity_dynamic
from particle.model import build_model
from particle.params import ConnectorParams
from particle.stability import (connector_strains, critical_time_step, release_strain_range,
                                resolve_time_step)
from particle.statics import check_stiffness, gravity_static

log = logging.getLogger(__name__)

GRAVITY_KIND = "forcecal.gravity"
GRAVITY_SCHEMA = 1
MODELS = ("calibrated", "baseline")
GRAVITY_EXPERIMENTS = ("gravity_static", "gravity_dynamic")
SCALARS = ("dt", "critical_dt", "static_time", "dynamic_time", "strain_min", "strain_max")


@dataclass(frozen=True, eq=False)
class ParticleGravity:
    """One particle model's gravity test.

    Attributes:
        static_displacement: (N, 3) float64, static sag [m].
        displacement: (S, N, 3) float64, dynamic displacements at the FE's record times [m];
            None without the dynamic release.
        dt: explicit time step used [s].
        critical_dt: stability limit of that step [s].
        static_time: wall time of the static solve [s].
        dynamic_time: wall time of the dynamic run [s], kernel compiled beforehand.
        strain_min, strain_max: most compressive / most tensile connector strain reached [1].
    """
    static_displacement: np.ndarray
    displacement: np.ndarray | None
    dt: float
    critical_dt: float
    static_time: float
    dynamic_time: float
    strain_min: float
    strain_max: float


@dataclass(frozen=True, eq=False)
class GravityRuns:
    """Everything in ``gravity.h5``.

    Attributes:
        problem: mesh, fixed nodes, test points, tracked node.
        time: (S,) float64, sample times [s].
        acceleration: (3,) float64, gravitational acceleration [m/s^2].
        models: model name (:data:`MODELS`) -> its runs.
        reference_fingerprint, params_fingerprint: SHA-256 of the input files.
        experiments: the gravity experiments run (``time`` is None without
            ``gravity_dynamic``).
    """
    problem: Problem
    time: np.ndarray | None
    acceleration: np.ndarray
    models: dict[str, ParticleGravity]
    reference_fingerprint: str = ""
    params_fingerprint: str = ""
    experiments: tuple[str, ...] = GRAVITY_EXPERIMENTS


def run_model(scene: Scene, problem: Problem, params: ConnectorParams, gravity: np.ndarray,
              times: np.ndarray | None, strain_range: tuple[float, float], name: str
              ) -> ParticleGravity:
    """Static sag and dynamic release of one parameter set (``times`` None: the static sag
    only, with the step the release would take).

    ``strain_range`` is where the springs were calibrated (and must be
    positive); the runs are refused (:class:`ParameterError`) if a spring's
    K(eps) becomes <= 0 at a strain they reach, and the strain extremes are
    recorded so that leaving the calibrated range can be reported. The
    explicit step is chosen for each connector's strain range of the release
    (:func:`release_strain_range` of the static sag, ``particle.strain_margin``),
    which the dynamic run verifies; an explicit ``particle.dt`` must be stable
    over the calibrated range as well.
    """
    model = build_model(problem, scene.material.density, params)
    t0 = time.perf_counter()
    static = gravity_static(model, gravity, load_steps=scene.gravity.static_load_steps,
                            strain_range=strain_range)
    t1 = time.perf_counter()
    check_stiffness(model, connector_strains(model, static), f"static sag of the {name} model")
    release = release_strain_range(model, static, scene.particle.strain_margin)
    if scene.particle.dt != "auto":
        release = (np.minimum(release[0], strain_range[0]),
                   np.maximum(release[1], strain_range[1]))
    critical = critical_time_step(model, strain_range=release, damping=scene.particle.damping)
    dt = resolve_time_step(scene.particle, critical)
    if times is None:
        eps = connector_strains(model, static)
        log.info("gravity, %s model: max static sag %.3g mm, strains [%.3g, %.3g], static "
                 "%.2f s (no dynamic release: not in the scene's experiments)", name,
                 1e3 * np.linalg.norm(static, axis=1).max(), eps.min(), eps.max(), t1 - t0)
        return ParticleGravity(static, None, dt, critical, t1 - t0, 0.0, float(eps.min()),
                               float(eps.max()))
    # a few steps first so that dynamic_time measures the simulation, not numba compiling
    # (or loading from its cache) this model's kernel specialisation
    gravity_dynamic(model, gravity, float(times[1]), dt, times[:2],
                    damping=scene.particle.damping, strain_range=release)
    t2 = time.perf_counter()
    dynamic = gravity_dynamic(model, gravity, float(times[-1]), dt, times,
                              damping=scene.particle.damping, strain_range=release)
    t3 = time.perf_counter()
    strain = np.vstack([connector_strains(model, static)[None], connector_strains(model, dynamic)])
    for t, sample in zip(times, strain[1:]):
        check_stiffness(model, sample, f"gravity dynamics of the {name} model at t = {t:.4g} s")
    log.info("gravity, %s model: max static sag %.3g mm, dt %.3g s (limit %.3g s), strains "
             "[%.3g, %.3g], static %.2f s, dynamic %.2f s (%d samples)", name,
             1e3 * np.linalg.norm(static, axis=1).max(), dt, critical, strain.min(),
             strain.max(), t1 - t0, t3 - t2, len(times))
    return ParticleGravity(static, dynamic, dt, critical, t1 - t0, t3 - t2,
                           float(strain.min()), float(strain.max()))


def run_gravity(scene: Scene, reference: Reference, connectors: dict[str, ConnectorParams],
                strain_range: tuple[float, float], *, reference_fingerprint: str = "",
                params_fingerprint: str = "") -> GravityRuns:
    """Run every model of :data:`MODELS` through the reference's gravity experiments.

    ``strain_range`` is the calibration's: where the calibrated springs are valid.
    """
    experiments = tuple(e for e in GRAVITY_EXPERIMENTS if scene.runs(e))
    for e in experiments:
        reference.require(e)
    g = np.asarray(scene.gravity.acceleration, dtype=np.float64)
    times = reference.gravity.time if "gravity_dynamic" in experiments else None
    missing = [m for m in MODELS if m not in connectors]
    if missing:
        raise DataFileError(f"params.h5 lacks connector parameters {missing}")
    models = {m: run_model(scene, reference.problem, connectors[m], g, times, strain_range, m)
              for m in MODELS}
    return GravityRuns(reference.problem, times, g, models, reference_fingerprint,
                       params_fingerprint, experiments)


def write_gravity(path: str | Path, runs: GravityRuns) -> None:
    """Write ``gravity.h5`` atomically (schema in the module docstring)."""
    with atomic_h5(path, GRAVITY_KIND, GRAVITY_SCHEMA) as fh:
        fh.attrs["acceleration"] = runs.acceleration
        fh.attrs["reference_fingerprint"] = runs.reference_fingerprint
        fh.attrs["params_fingerprint"] = runs.params_fingerprint
        fh.attrs["experiments"] = json.dumps(list(runs.experiments))
        write_problem(fh, runs.problem)
        if runs.time is not None:
            put(fh, "time", runs.time, "s", "sample times of the dynamic run (S,)")
        for name, r in runs.models.items():
            g = fh.create_group(name)
            put(g, "static_displacement", r.static_displacement, "m", "static sag (N, 3)")
            if r.displacement is not None:
                put(g, "displacement", r.displacement, "m", "dynamic displacements (S, N, 3)")
            for k in SCALARS:
                g.attrs[k] = getattr(r, k)


def read_gravity(path: str | Path) -> GravityRuns:
    """Read ``gravity.h5`` back (kind, schema, shapes and finiteness checked)."""
    with open_h5(path, GRAVITY_KIND, GRAVITY_SCHEMA) as fh:
        problem = read_problem(fh)
        experiments = (tuple(json.loads(fh.attrs["experiments"])) if "experiments" in fh.attrs
                       else GRAVITY_EXPERIMENTS)
        dynamic = "gravity_dynamic" in experiments
        times = get(fh, "time", (None,), dtype="float") if dynamic else None
        n = problem.mesh.n_vertices
        models = {}
        for name in MODELS:
            if name not in fh:
                raise DataFileError(f"{path}:/{name} is missing")
            a = fh[name].attrs
            models[name] = ParticleGravity(
                get(fh, f"{name}/static_displacement", (n, 3), dtype="float"),
                get(fh, f"{name}/displacement", (len(times), n, 3), dtype="float")
                if dynamic else None,
                *(float(a[k]) for k in SCALARS))
        return GravityRuns(problem, times, np.asarray(fh.attrs["acceleration"], dtype=float),
                           models, str(fh.attrs["reference_fingerprint"]),
                           str(fh.attrs["params_fingerprint"]), experiments)
