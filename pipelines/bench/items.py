"""The items of ``make bench`` that measure the default scene (:mod:`pipelines.bench.driver`
runs them in order): the default pipeline run, its calibration, the particle time-step
sweep, the FE discretisation study, the 1- and 2-rank reference timings and the particle
engine (kernel throughput, 3 s gravity dynamics, term skipping, haptic latency,
evaluators). Long FE results are kept in the bench cache under :func:`fe_key`."""

from __future__ import annotations

import datetime
import json
import logging
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any, Callable

import numpy as np

from forcecal.errors import DataFileError, ForcecalError
from forcecal.h5io import Reference, atomic_path, read_reference
from forcecal.problem import build_problem, load_mesh
from forcecal.provenance import FE_BENCH, json_digest, section_fingerprint
from forcecal.scene import Scene
from forcecal.sections import REFERENCE_SECTIONS
from pipelines.bench import configs as bc
from pipelines.report import gravity_dynamic_error, read_report
from pipelines.runners.reference import mpirun_environment
from pipelines.runners.common import GRAVITY, PARAMS, REFERENCE

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parents[2]
SEED_FILES = (REFERENCE, PARAMS, "gravity.h5", "report.json")
GOALS = {"numpy_ratio": 20.0, "gravity_3s_s": 0.05, "haptic_us": 100.0, "calibration_s": 300.0,
         "reference_2ranks_s": 900.0, "punch_body_calibration_s": 120.0}
PAPER = {"calibration_s": 8 * 3600.0, "gravity_3s_s": 1.3}


def now_utc() -> str:
    """The current UTC time, ISO 8601 to the second."""
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


#: marker file of a bench cache started with ``--cold`` (:func:`runs_source`)
COLD_MARKER = "COLD"


def runs_source(cache: Path, name: str) -> Path | None:
    """The scene's ``runs/<name>/`` folder (``make demo``'s), whose current work the bench may
    adopt; None in a cache started cold (``cache/COLD``): a cold bench computes everything
    itself, so every item's time is a cold time."""
    return None if (cache / COLD_MARKER).is_file() else ROOT / "runs" / name


def default_folder(cache: Path) -> Path:
    """Where the bench's default pipeline run lives in the bench cache ``cache`` (the studies
    that reuse its work read it there)."""
    return cache / "runs" / "default"


def seed_folder(source: Path, folder: Path) -> bool:
    """Copy a finished pipeline run (:data:`SEED_FILES` and its stage cache records) from
    ``source`` into ``folder`` when it finished later than the folder's own (or the folder
    has none); the pipeline's cache then decides what is still valid. True if copied."""
    finished = source / "cache" / "report.json"
    own = folder / "cache" / "report.json"
    if not finished.is_file() or (own.is_file()
                                  and own.stat().st_mtime >= finished.stat().st_mtime):
        return False
    (folder / "cache").mkdir(parents=True, exist_ok=True)
    for name in SEED_FILES:
        if (source / name).is_file():
            shutil.copy2(source / name, folder / name)
    for record in (source / "cache").glob("*.json"):
        shutil.copy2(record, folder / "cache" / record.name)
    log.info("bench: seeded %s from %s", folder, source)
    return True


def seed_default(scene: Scene, cache: Path) -> None:
    """Seed the default run's folder (:func:`default_folder`) from a finished run of the
    scene in ``runs/<name>/`` (e.g. from ``make demo``; never in a cold bench,
    :func:`runs_source`), see :func:`seed_folder`."""
    source = runs_source(cache, scene.name)
    if source is not None:
        seed_folder(source, default_folder(cache))


def default_run(scene: Scene, cache: Path, *, ranks: int, progress: bool
                ) -> tuple[Path, dict[str, Any]]:
    """The default scene's full pipeline, up to date, in :func:`default_folder`; its row."""
    folder = default_folder(cache)
    seed_default(scene, cache)
    return folder, bc.pipeline_row(scene, folder, ranks=ranks, progress=progress)


# ---------------------------------------------------------------------------- particle dt axis

def calibrated_release(scene: Scene, folder: Path, reference: Reference):
    """(calibrated Model, the ranges of its release as keywords ``strain_range`` and
    ``volume_range``) as the gravity stage has them.

    The ranges are :func:`~particle.experiments.release_ranges` of the stage's own static
    sag (``gravity.h5``), so steps chosen for them are the ones ``make demo`` uses; without
    that file (the gravity stage failed) the default strain range +-0.5, with a warning.
    """
    from calibration import read_params
    from particle.experiments import release_ranges
    from particle.model import build_model
    from particle.stability import DEFAULT_STRAIN_RANGE
    from pipelines.gravity import read_gravity

    params = read_params(folder / PARAMS)
    model = build_model(reference.problem, scene.material.density,
                        params.connectors["calibrated"],
                        volume_element=scene.particle.volume_element)
    if not (folder / GRAVITY).is_file():
        log.warning("bench: no %s (the gravity stage failed): particle gravity runs use the "
                    "default strain range %s", folder / GRAVITY, DEFAULT_STRAIN_RANGE)
        return model, {"strain_range": DEFAULT_STRAIN_RANGE, "volume_range": None}
    static = read_gravity(folder / GRAVITY).models["calibrated"].static_displacement
    strains, volumes = release_ranges(model, static, scene.particle, params.strain.bounds)
    return model, {"strain_range": strains, "volume_range": volumes}


def dt_sweep(scene: Scene, folder: Path, fractions: tuple[float, ...]) -> list[dict[str, Any]]:
    """Gravity dynamics of the calibrated model at several steps (fractions of the limit).

    The limit is the gravity stage's (over the release's strain range, which each
    run verifies); the scene's ``particle.dt_safety`` is one of the fractions.
    Errors at the tracked vertex (:func:`pipelines.report.gravity_dynamic_error`):
    ``gravity_dynamic`` against the FE; ``overall`` (the axis's Pareto error, the
    time-discretisation error the step controls) against the smallest step's run.
    """
    from particle.experiments import gravity_dynamic
    from particle.stability import critical_time_step

    reference = read_reference(folder / REFERENCE)
    model, release = calibrated_release(scene, folder, reference)
    damping = scene.particle.damping
    critical = critical_time_step(model, damping=damping, **release)
    g = np.asarray(scene.gravity.acceleration, dtype=float)
    times = reference.gravity.time
    node = reference.problem.tracked_node
    fe = reference.gravity.displacement[:, node]
    gravity_dynamic(model, g, float(times[2]), critical, times[:3], damping=damping,
                    **release)  # compile
    if scene.particle.dt == "auto":
        fractions = (*fractions, scene.particle.dt_safety)
    runs = []
    for f in sorted(set(fractions)):
        u, wall = bc.timed(gravity_dynamic, model, g, float(times[-1]), f * critical, times,
                           damping=damping, **release)
        runs.append((f, u[:, node], wall))
    finest = runs[0][1]
    default = scene.particle.dt_safety if scene.particle.dt == "auto" else None
    return [{"axis": "particle dt", "label": f"{f:g} x limit",
             "config": {"dt_fraction": f, "dt_s": f * critical, "critical_dt_s": critical},
             "stage": f"gravity dynamics (particle, {times[-1]:g} s)", "wall_s": wall,
             "errors": {"gravity_dynamic": gravity_dynamic_error(fe, u),
                        "overall": gravity_dynamic_error(finest, u) if f > runs[0][0] else 0.0},
             "default": default is not None and abs(f - default) < 1e-12}
            for f, u, wall in runs]


# ---------------------------------------------------------------------------- FE axis

def fe_key(scene: Scene) -> str:
    """Identity of an FE computation: the code of the FE runs the bench starts (the reference
    and the discretisation study, :data:`forcecal.provenance.FE_BENCH`), the scene's reference
    sections, the mesh."""
    return json_digest({"code": FE_BENCH.digest(),
                        "scene": section_fingerprint(scene, *REFERENCE_SECTIONS),
                        "mesh": load_mesh(scene).fingerprint()})


def cached(path: Path, key: str, compute: Callable[[], Any]) -> Any:
    """``compute()``'s JSON result, kept in ``path`` and reused while ``key`` is unchanged."""
    if path.is_file():
        try:
            record = json.loads(path.read_text())
            if record.get("key") == key:
                log.info("bench: reusing %s (same code and scene)", path)
                return record["value"]
        except ValueError:
            log.warning("bench: ignoring unreadable %s", path)
    value = compute()
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps({"key": key, "value": value,
                                   "measured": now_utc()}, indent=1))
    return value


def discretisation_study_on(scene: Scene, ranks: int, folder: Path) -> dict[str, Any]:
    """:func:`reference_fe.sensitivity.discretisation_study` of ``scene`` with its variants
    shared out over ``ranks`` MPI processes (one process: in this one); raises
    :class:`ForcecalError` if it fails."""
    mpirun = shutil.which("mpirun")
    if ranks == 1 or mpirun is None:
        from reference_fe.sensitivity import discretisation_study
        return discretisation_study(scene)
    out = folder / "fe_study.partial.json"
    cmd = [mpirun, "-n", str(ranks), sys.executable, "-m", "reference_fe.sensitivity",
           "--scene", str(scene.path), "--out", str(out)]
    log.info("bench: FE discretisation study on %d ranks: %s", ranks, " ".join(cmd))
    if subprocess.run(cmd, env=mpirun_environment(), stdin=subprocess.DEVNULL).returncode != 0:
        raise ForcecalError(f"the FE discretisation study on {ranks} ranks failed (message "
                            "above)")
    try:
        return json.loads(out.read_text())
    finally:
        out.unlink(missing_ok=True)


def fe_rows(scene: Scene, cache: Path, ranks: int = 1) -> list[dict[str, Any]]:
    """The FE discretisation study as rows: wall time of the variant's experiments, change of
    the max static sag (``overall``) and of the full-depth indentation forces against the
    finest variant (P2 on the uniformly refined mesh). The variants run on ``ranks``
    processes at once (each variant's wall time is its own process's)."""
    def study() -> dict:
        try:
            return discretisation_study_on(scene, ranks, cache)
        except ForcecalError as exc:  # kept too: retried only when the FE code changes
            return {"failed": f"{type(exc).__name__}: {exc}"}

    result = cached(cache / "fe_study.json", fe_key(scene), study)
    if "failed" in result:
        log.warning("bench: the FE discretisation study failed: %s", result["failed"])
        return [{"axis": "FE discretisation", "label": "study", "config": {},
                 "stage": "FE discretisation study", "wall_s": None, "errors": None,
                 "default": False, "failed": result["failed"]}]
    variants = result["variants"]
    finest = next(k for k in variants if k.endswith("refined"))
    ref_f = np.asarray(variants[finest]["indentation_force_N"])
    ref_sag = variants[finest]["max_sag_m"]
    own = f"{scene.fe.element} q={scene.fe.quadrature_degree}"
    rows = []
    for label, v in variants.items():
        t = v["wall_time_s"]
        force = float(np.mean(np.abs(np.asarray(v["indentation_force_N"]) / ref_f - 1)))
        sag = abs(v["max_sag_m"] / ref_sag - 1)
        rows.append({"axis": "FE discretisation", "label": label,
                     "config": {"element": v["element"], "quadrature_degree":
                                v["quadrature_degree"], "dofs": v["n_dofs"],
                                "refined": label.endswith("refined")},
                     "stage": "FE model build + indentation of the study's points + static sag",
                     "wall_s": t["build"] + t["indentation_per_point"] * len(result["points"])
                     + t["gravity_static"],
                     # the vertex force has no mesh-converged value (docs/limitations.md): the
                     # sag is the quantity the refined mesh can say something about
                     "errors": {"force_change_vs_finest": force, "overall": sag},
                     "default": label == own})
    return rows


# ---------------------------------------------------------------------------- reference timings

def _complete_run_seconds(reference: Reference) -> tuple[int, float] | None:
    """(ranks, wall s) of the run that wrote ``reference``, or None if it was resumed.

    A resumed run's wall time covers only its own part: its items' compute time
    (summed over ranks) then exceeds ranks x wall time.
    """
    meta = reference.meta
    try:
        ranks, t = int(meta["n_ranks"]), json.loads(meta["timings_s"])
        items = sum(t[k] for k in ("indentation", "relaxation", "gravity_static",
                                   "gravity_dynamic"))
        total = float(t["total"])
    except (KeyError, TypeError, ValueError):
        return None
    return (ranks, total) if items <= 1.05 * ranks * total else None


def measure_reference(scene: Scene, ranks: int, folder: Path, progress: bool) -> float:
    """Compute the scene's full reference with ``ranks`` MPI ranks; its wall time [s]."""
    out = folder / f"reference-{ranks}rank" / REFERENCE
    cmd = [sys.executable, "-m", "reference_fe", "--scene", str(scene.path), "--out", str(out)]
    if not progress:
        cmd.append("--no-progress")
    if ranks > 1:
        mpirun = shutil.which("mpirun")
        if mpirun is None:
            raise DataFileError("mpirun is not on the PATH: cannot time the reference on "
                                f"{ranks} ranks")
        cmd = [mpirun, "-n", str(ranks)] + cmd
    log.info("bench: timing the full reference on %d rank(s): %s", ranks, " ".join(cmd))
    if subprocess.run(cmd, env=mpirun_environment(), stdin=subprocess.DEVNULL).returncode != 0:
        raise DataFileError(f"the timed reference run on {ranks} rank(s) failed (message above)")
    measured = _complete_run_seconds(read_reference(out))
    shutil.rmtree(out.parent)
    if measured is None or measured[0] != ranks:
        raise DataFileError(f"the timed reference run on {ranks} rank(s) did not record a "
                            "complete wall time")
    return measured[1]


def reference_timings(scene: Scene, default_folder: Path, cache: Path, progress: bool,
                      ranks: tuple[int, ...] = (1, 2)) -> dict[str, Any]:
    """Wall time of the full reference with each rank count of ``ranks`` (1 and/or 2; the
    default run's own timing where it has that count, see :mod:`pipelines.bench.driver`);
    ``wall_s_1rank`` / ``wall_s_2ranks`` None for a count not asked for."""
    key = fe_key(scene)
    path = cache / "reference_timing.json"
    record = {"key": key, "runs": {}}
    if path.is_file():
        old = json.loads(path.read_text())
        if old.get("key") == key:
            record = old
            log.info("bench: reusing %s (same code and scene)", path)
    # the default run's reference is up to date with this code (its pipeline just checked):
    # its own timing replaces an older one with the same rank count
    default_reference = read_reference(default_folder / REFERENCE)
    own = _complete_run_seconds(default_reference)
    if own is not None:
        record["runs"][str(own[0])] = {"wall_s": own[1], "source": "default pipeline run",
                                       "measured": str(default_reference.meta.get("created"))}
    for count in ranks:
        if str(count) not in record["runs"]:
            record["runs"][str(count)] = {
                "wall_s": measure_reference(scene, count, cache, progress),
                "source": "bench run", "measured": now_utc(),
                "load_average": os.getloadavg()[1]}  # 5-minute mean at the end
            with atomic_path(path) as tmp:  # kept at once: the next one takes minutes
                tmp.write_text(json.dumps(record, indent=1))
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(record, indent=1))
    runs = {str(count): record["runs"][str(count)] for count in ranks}
    return {"wall_s_1rank": runs["1"]["wall_s"] if "1" in runs else None,
            "wall_s_2ranks": runs["2"]["wall_s"] if "2" in runs else None,
            "goal_2ranks_s": GOALS["reference_2ranks_s"], "runs": runs,
            "test_points": len(build_problem(scene).test_points)}


# ---------------------------------------------------------------------------- particle engine

def particle_items(scene: Scene, folder: Path, quick: bool) -> dict[str, Any]:
    """Kernel throughput, gravity dynamics vs FE, term skipping, haptics, evaluators."""
    import numba

    from forcecal.liver_mesh import generate_liver
    from pipelines.bench import particle_engine as pb

    numba.set_num_threads(1)
    reference = read_reference(folder / REFERENCE)
    gravity_errors = {"calibrated": None, "baseline": None}  # None: the gravity stage failed
    if (folder / "report.json").is_file():
        report = read_report(folder / "report.json")
        gravity_errors = {"calibrated": report["errors"]["gravity_dynamic"],
                          "baseline": report["baseline_errors"]["gravity_dynamic"]}
    problem = reference.problem
    g = np.asarray(scene.gravity.acceleration, dtype=float)
    uniform = pb.scene_model(scene, problem.mesh, problem.fixed)
    large_mesh = generate_liver(0.012 if quick else pb.LARGE_MESH_LENGTH)
    large = pb.scene_model(scene, large_mesh)
    steps = 500 if quick else 2000
    liver_rate = pb.step_throughput(uniform, steps=steps)
    large_rate = pb.step_throughput(large, steps=steps // 4)
    calibrated, release = calibrated_release(scene, folder, reference)
    dynamics = pb.gravity_realtime(calibrated, g, duration=scene.gravity.duration,
                                   record_interval=scene.gravity.record_interval,
                                   safety=scene.particle.dt_safety, **release)
    fe_dynamic = json.loads(reference.meta["timings_s"])["gravity_dynamic"]
    skip = pb.skip_timings(uniform, g, duration=1.0 if quick else scene.gravity.duration)
    top = int(np.argmax(large_mesh.vertices[:, 2]))
    haptic = {"liver": pb.haptic_latency(uniform, int(problem.test_points[0]),
                                         problem.normals[0], calls=500 if quick else 2000),
              "large": pb.haptic_latency(large, top, np.array([0.0, 0.0, -1.0]),
                                         calls=200 if quick else 1000)}
    if numba.config.NUMBA_NUM_THREADS >= 2:  # the opt-in 2-thread session, mesh renumbered
        haptic["large_2threads"] = pb.haptic_latency(
            large, top, np.array([0.0, 0.0, -1.0]), calls=200 if quick else 1000, threads=2,
            renumber=True)
    return {
        "kernel": {"connectors": liver_rate["connectors"],
                   "updates_per_s": liver_rate["compiled_updates_per_s"],
                   "numpy_ratio": liver_rate["speedup"], "liver": liver_rate,
                   "large": large_rate, "goal_numpy_ratio": GOALS["numpy_ratio"]},
        "gravity_dynamic": {"particle_s": dynamics["wall_s"], "particle_cpu_s": dynamics["cpu_s"],
                            "fe_s": fe_dynamic, "speedup": fe_dynamic / dynamics["wall_s"],
                            "error": gravity_errors["calibrated"],
                            "baseline_error": gravity_errors["baseline"],
                            "dt_s": dynamics["dt_s"], "steps": dynamics["steps"],
                            "duration_s": dynamics["duration_s"],
                            "goal_s": GOALS["gravity_3s_s"], "paper_s": PAPER["gravity_3s_s"]},
        "skip": [{"scene": name, "full_s": row["no_skip"]["cpu_s"],
                  "skipped_s": row["skip"]["cpu_s"], "full_wall_s": row["no_skip"]["wall_s"],
                  "skipped_wall_s": row["skip"]["wall_s"], "steps": skip["steps"]}
                 for name, row in skip.items() if isinstance(row, dict)],
        "haptic": haptic,
        "evaluators": pb.evaluator_timings(uniform, problem, scene, points=2 if quick else 4),
    }


def calibration_item(folder: Path) -> dict[str, Any]:
    """Wall time and evaluation counts of the default calibration (from its params.h5)."""
    from calibration import read_params
    result = read_params(folder / PARAMS)
    return {"wall_s": result.wall_time, "evaluations": result.evaluations.get("point_curves"),
            "cost_evaluations": {k: v for k, v in result.evaluations.items()
                                 if k != "point_curves"},
            "stage_times_s": result.stage_times, "goal_s": GOALS["calibration_s"],
            "paper_s": PAPER["calibration_s"]}
