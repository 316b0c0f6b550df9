"""Run time vs error: the configurations of ``make bench``, each measured in one run.

Axes (:func:`pareto_rows`), each varied alone around the default scene:

* **particle dt**: the explicit step as a fraction of the estimated limit;
  3 s of gravity dynamics of the calibrated model, error against the FE and
  against the smallest step;
* **mesh**: characteristic length of the generated liver. Every level needs
  its own FE reference, so each runs a *reduced* experiment set: 8 calibration
  points (spread over the free surface), 8 held-out points (the least a scene
  may have), the scene's indentation and relaxation schedules, the static sag and the first
  :data:`MESH_GRAVITY_DURATION` s of the gravity release (the FE dynamic run
  is the reference's most expensive item); the default level is run with that
  reduced set too, so the three are comparable;
* **calibration points**, **Nelder-Mead budget**, **local tuning**: the
  calibration on the default mesh; the FE curves of the points are taken from
  the default reference (a subset of its points for fewer calibration points:
  each FE work item depends only on its own point, so the slice equals what a
  run on those points would compute);
* **FE discretisation**: :func:`reference_fe.sensitivity.discretisation_study`.

Every configuration except the FE study is a scene derived from the default
(``scene.toml`` in its folder) run through the cached pipeline
(:func:`pipelines.stages.run_pipeline`) in ``<bench>/cache/runs/<slug>/``, so a
configuration is recomputed only when its inputs or the code changed.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from forcecal.errors import ForcecalError
from forcecal.h5io import Reference, read_reference, write_reference
from forcecal.point_selection import fixed_nodes, select_held_out_points
from forcecal.problem import load_mesh
from forcecal.provenance import file_digest
from forcecal.scene import Scene, load_scene, scene_from_dict
from pipelines.report import fe_timings, read_report
from forcecal.sections import REFERENCE_SECTIONS
from pipelines.runners.common import PARAMS, REFERENCE
from pipelines.stages import run_pipeline

log = logging.getLogger(__name__)

# the gravity errors of a pipeline run (dimensionless, see pipelines.report)
GRAVITY_ERRORS = ("gravity_static", "gravity_dynamic")
REDUCED_POINTS = (8, 8)  # calibration, held-out points of the mesh study
# the settings of each pipeline axis besides the default's ({quick: ...}); ``make bench`` runs
# the first :data:`HEADLINE_SETTINGS` of each (the coarse mesh level, the fewest points, the
# smallest budget), ``make bench-full`` all of them
MESH_FACTORS = {False: (1.375, 1.0, 0.77), True: (1.25, 1.0, 0.8)}  # 0.025 / 0.0182 / 0.014 m
POINT_COUNTS = {False: (8, 16), True: (3,)}
BUDGET_SCALES = {False: (0.1, 0.25), True: (0.25,)}
HEADLINE_SETTINGS = {"mesh": 2, "calibration points": 1, "Nelder-Mead budget": 1}
MESH_GRAVITY_DURATION = 1.0  # s of gravity dynamics in the mesh study
BUDGET_KEYS = ("static_max_evaluations", "relaxation_max_evaluations", "local_max_evaluations")


@dataclass(frozen=True)
class Config:
    """One pipeline configuration of the study.

    Attributes:
        axis: what is varied ("mesh", "calibration points", ...).
        label: short human label, unique within the axis.
        values: the varied settings (JSON-ready), as reported in ``bench.json``.
        changes: scene changes ({section: {key: value}}) from the default scene.
        reference: where the FE reference comes from: ``"default"`` (the default
            run's), ``"slice"`` (its curves at this scene's test points) or
            ``"compute"`` (the pipeline computes it).
        default: this is the default scene's setting on this axis.
    """
    axis: str
    label: str
    values: dict[str, Any]
    changes: dict[str, dict[str, Any]] = field(default_factory=dict)
    reference: str = "default"
    default: bool = False

    @property
    def slug(self) -> str:
        return "".join(c if c.isalnum() or c in "-." else "-" for c in
                       f"{self.axis}-{self.label}").lower()


def scene_toml(data: dict[str, Any]) -> str:
    """TOML text of a scene dictionary (``Scene.to_dict`` form: scalars, lists, tables)."""
    top = [f"{k} = {json.dumps(v)}" for k, v in data.items() if not isinstance(v, dict)]
    tables = [f"\n[{k}]\n" + "\n".join(f"{kk} = {json.dumps(vv)}" for kk, vv in v.items())
              for k, v in data.items() if isinstance(v, dict)]
    return "\n".join(top) + "\n" + "\n".join(tables) + "\n"


def derived_scene(base: Scene, name: str, changes: dict[str, dict[str, Any]],
                  folder: Path, *, experiments: tuple[str, ...] | None = None) -> Scene:
    """``base`` with ``changes`` (and ``experiments`` if given), no figures or fields, written
    to ``folder/scene.toml`` and loaded.

    A mesh file is referred to by its absolute path, so the copy finds it.
    """
    data = json.loads(json.dumps(base.to_dict(), default=list))
    data["name"] = name
    if experiments is not None:
        data["experiments"] = list(experiments)
    if base.mesh_source_path() is not None:
        data["mesh"]["source"] = str(base.mesh_source_path())
    data["outputs"] = {"figures": False, "fields": False}
    for section, values in changes.items():
        data[section].update(values)
    scene_from_dict(data)  # refuse a bad configuration before writing anything
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "scene.toml"
    text = scene_toml(data)
    if not path.is_file() or path.read_text() != text:
        path.write_text(text)
    return load_scene(path)


def sliced_reference(reference: Reference, scene: Scene) -> Reference:
    """The default reference restricted to ``scene``'s test points (a subset of its own)."""
    from forcecal.problem import build_problem
    from reference_fe.keys import experiment_keys

    problem = build_problem(scene, reference.problem.mesh)
    index = {int(p): k for k, p in enumerate(reference.problem.test_points)}
    rows = np.array([index[int(p)] for p in problem.test_points])

    def take(curves):
        return dataclasses.replace(curves, force=curves.force[rows],
                                   force_normal=curves.force_normal[rows])

    # the keys a run of this scene would record, so the pipeline adopts the slice: every FE
    # work item depends on its own point only (equal to a computed one bit for bit)
    keys = experiment_keys(scene, problem.mesh.fingerprint())
    held = json.loads(reference.meta.get("experiment_keys", "{}"))
    meta = {**reference.meta, "scene_fingerprint": scene.fingerprint(*REFERENCE_SECTIONS),
            "experiment_keys": json.dumps({e: keys[e] for e in held})}
    return dataclasses.replace(reference, problem=problem, indentation=take(reference.indentation),
                               relaxation=take(reference.relaxation), meta=meta)


def seed_reference(config: Config, scene: Scene, default_out: Path, folder: Path) -> None:
    """Put the default run's reference (whole or sliced) where the pipeline will adopt it.

    Rewritten only when the default reference changed (its digest is kept in
    ``seed.json``), so an unchanged seed keeps every later stage cached.
    """
    source = default_out / REFERENCE
    digest = file_digest(source)
    marker = folder / "seed.json"
    if (folder / REFERENCE).is_file() and marker.is_file() and json.loads(
            marker.read_text()).get("source") == digest:
        return
    if config.reference == "default":
        shutil.copy2(source, folder / REFERENCE)  # adopted by its experiment keys and content
    else:
        write_reference(folder / REFERENCE, sliced_reference(read_reference(source), scene))
    marker.write_text(json.dumps({"source": digest}))


def pipeline_row(scene: Scene, folder: Path, *, ranks: int, progress: bool) -> dict[str, Any]:
    """Bring ``scene``'s pipeline in ``folder`` up to date; its measurements as a row.

    Held-out curve errors and wall times come from the reference and the
    calibration; if the gravity stage fails (a calibrated model without a
    static equilibrium, say) the row keeps them and says why its gravity
    errors are missing. A failing reference or calibration raises.
    """
    from calibration import read_params

    ran = [o.stage for o in run_pipeline(scene, folder, until="calibrate", progress=progress,
                                         ranks=ranks) if o.ran]
    params = read_params(folder / PARAMS)
    summary = params.error_summary()["calibrated"]
    errors: dict[str, float | None] = {f"{e}_held_out": summary[e].get("held_out_mean")
                                       for e in ("indentation", "relaxation")}
    errors["overall"] = float(np.mean(list(errors.values())))
    # what the fit itself reaches at the points it was fitted to (not the Pareto error)
    errors.update({f"{e}_calibrated": summary[e]["calibration_mean"]
                   for e in ("indentation", "relaxation")})
    row = {"reference_s": fe_timings(read_reference(folder / REFERENCE))["total"],
           "calibration_s": params.wall_time, "connectors": int(len(params.problem.mesh.edges)),
           "test_points": [len(params.problem.calibration), len(params.problem.held_out)],
           "folder": str(folder)}
    try:
        ran += [o.stage for o in run_pipeline(scene, folder, progress=progress, ranks=ranks)
                if o.ran]
        report = read_report(folder / "report.json")
        errors.update({k: report["errors"][k] for k in GRAVITY_ERRORS})
    except ForcecalError as exc:
        log.warning("bench: %s: gravity stage failed: %s", scene.name, exc)
        errors.update(dict.fromkeys(GRAVITY_ERRORS))
        row["gravity_failed"] = f"{type(exc).__name__}: {exc}"
    return {**row, "errors": errors, "ran": ran}


def run_config(config: Config, base: Scene, default_out: Path, root: Path, *, ranks: int,
               progress: bool) -> dict[str, Any]:
    """One configuration's row of ``bench.json:/pareto`` (its pipeline brought up to date)."""
    folder = root / config.slug
    scene = derived_scene(base, f"bench-{config.slug}", config.changes, folder)
    row = {"axis": config.axis, "label": config.label, "config": config.values,
           "default": config.default}
    if config.reference != "compute":
        seed_reference(config, scene, default_out, folder)
    try:
        measured = pipeline_row(scene, folder, ranks=ranks, progress=progress)
    except ForcecalError as exc:  # a configuration the method cannot handle is a result too
        log.warning("bench: configuration %s / %s failed: %s", config.axis, config.label, exc)
        return {**row, "stage": "calibration", "wall_s": None, "errors": None,
                "failed": f"{type(exc).__name__}: {exc}", "folder": str(folder)}
    if config.axis == "mesh":
        stage = "reference + calibration"
        wall = measured["reference_s"] + measured["calibration_s"]
    else:
        stage, wall = "calibration", measured["calibration_s"]
    return {**row, "stage": stage, "wall_s": wall, **measured}


def default_row(measured: dict[str, Any], scene: Scene) -> dict[str, Any]:
    """The default scene's own run (:func:`pipeline_row`) as a row (axis ``default``)."""
    return {"axis": "default", "label": scene.name, "config": {}, "stage": "calibration",
            "wall_s": measured["calibration_s"], "default": True, **measured}


def reduced_points(scene: Scene, characteristic_length: float) -> list[int]:
    """The mesh study's calibration points: spread over the free surface of that mesh."""
    mesh = load_mesh(dataclasses.replace(
        scene, mesh=dataclasses.replace(scene.mesh, characteristic_length=characteristic_length)))
    f = scene.fixed
    fixed = fixed_nodes(mesh, f.axis, f.side, f.tolerance)
    picked = select_held_out_points(mesh, fixed, np.zeros(0, np.int64), REDUCED_POINTS[0])
    return [int(p) for p in picked]


def configs(scene: Scene, quick: bool, full: bool = True) -> list[Config]:
    """The pipeline configurations of the study (the particle dt and FE axes are not
    pipelines); ``full`` False: the headline's (:data:`HEADLINE_SETTINGS`)."""
    def settings(axis: str, values: tuple) -> tuple:
        return values if full else values[:HEADLINE_SETTINGS[axis]]

    out = []
    h0 = scene.mesh.characteristic_length
    factors = settings("mesh", MESH_FACTORS[quick])
    if scene.mesh.source == "generate":
        n_cal, n_held = (4, REDUCED_POINTS[1]) if quick else REDUCED_POINTS
        duration = min(scene.gravity.duration, MESH_GRAVITY_DURATION)
        for f in factors:
            h = round(h0 * f, 3) if f != 1.0 else h0
            out.append(Config("mesh", f"h={h:g} m", {"characteristic_length_m": h,
                                                     "points": [n_cal, n_held],
                                                     "gravity_duration_s": duration},
                              {"mesh": {"characteristic_length": h},
                               "test_points": {"calibration": reduced_points(scene, h)[:n_cal],
                                               "held_out": "auto", "n_held_out": n_held},
                               "gravity": {"duration": duration}},
                              reference="compute", default=f == 1.0))
    cal, held = _default_test_points(scene)
    for n in settings("calibration points", POINT_COUNTS[quick]):
        picked = [cal[i] for i in np.linspace(0, len(cal) - 1, n).round().astype(int)]
        # the held-out points stay the default's ('auto' would pick others for fewer points)
        out.append(Config("calibration points", f"{n} points", {"calibration_points": n},
                          {"test_points": {"calibration": picked, "held_out": held}},
                          reference="slice"))
    c = scene.calibration
    for scale in settings("Nelder-Mead budget", BUDGET_SCALES[quick]):
        budgets = {k: max(1, round(scale * getattr(c, k))) for k in BUDGET_KEYS}
        out.append(Config("Nelder-Mead budget", f"x{scale:g}", {"budget_scale": scale, **budgets},
                          {"calibration": budgets}))
    out.append(Config("local tuning", "off", {"local": False}, {"calibration": {"local": False}}))
    return out


def _default_test_points(scene: Scene) -> tuple[list[int], list[int]]:
    """The default scene's (calibration, held-out) points."""
    from forcecal.problem import build_problem
    problem = build_problem(scene)
    return [int(p) for p in problem.calibration], [int(p) for p in problem.held_out]


def axis_defaults(scene: Scene, default: dict[str, Any]) -> list[dict[str, Any]]:
    """The default run repeated as the default point of the calibration axes."""
    c = scene.calibration
    values = {"calibration points": {"calibration_points": default["test_points"][0]},
              "Nelder-Mead budget": {"budget_scale": 1.0,
                                     **{k: getattr(c, k) for k in BUDGET_KEYS}},
              "local tuning": {"local": c.local}}
    labels = {"calibration points": f"{default['test_points'][0]} points",
              "Nelder-Mead budget": "x1", "local tuning": "on" if c.local else "off"}
    return [{**default, "axis": axis, "label": labels[axis], "config": v}
            for axis, v in values.items()]


def non_dominated(points: list[tuple[float, ...]]) -> list[bool]:
    """Whether each point is Pareto-optimal, smaller being better in every coordinate: no
    other point is at least as good in all of them and strictly better in one."""
    return [not any(q != p and all(b <= a for a, b in zip(p, q)) for q in points)
            for p in points]


def pareto_front(rows: list[dict[str, Any]], error: str = "overall") -> list[bool]:
    """Whether each row is Pareto-optimal in (wall_s, errors[error]): nothing is as fast
    and as accurate with one of the two strictly better."""
    return non_dominated([(r["wall_s"], r["errors"][error]) for r in rows])


def mark_fronts(rows: list[dict[str, Any]]) -> None:
    """Set ``on_front`` of every row, per axis, on the axis's primary error (``errors.overall``);
    failed configurations are never on it. The ``default`` row is no axis of its own (alone
    it would trivially be on a front): it is on the front when the default setting is on the
    front of every axis it takes part in."""
    for row in rows:
        row["on_front"] = False
    for axis in dict.fromkeys(r["axis"] for r in rows if r["axis"] != "default"):
        members = [r for r in rows if r["axis"] == axis and "failed" not in r]
        for r, on in zip(members, pareto_front(members)):
            r["on_front"] = on
    defaults = [r["on_front"] for r in rows if r["default"] and r["axis"] != "default"]
    for row in rows:
        if row["axis"] == "default":
            row["on_front"] = bool(defaults) and all(defaults)


def timed(fn, *args, **kwargs) -> tuple[Any, float]:
    """(result, wall seconds) of one call."""
    t0 = time.perf_counter()
    result = fn(*args, **kwargs)
    return result, time.perf_counter() - t0
