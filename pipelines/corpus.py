"""The corpus run (``make corpus``): every ``scenes/corpus/*.toml`` through the whole pipeline.

Each scene runs as its own ``python -m pipelines demo --scene S --out runs/corpus/<stem>``
process, so a scene that crashes (or is refused) cannot stop the others; its output and
log lines go to ``runs/corpus/logs/<stem>.log``, its stage transitions and its
``error:`` line to the terminal. Resuming is the pipeline's own: every stage is
cached by content (``pipelines.stages``), so a scene whose report is up to date
runs none of its stages again (its process only checks the caches: seconds), and
an interrupted one resumes from its finished FE work items and calibration checkpoint.

Scenes run one after the other, smallest mesh first: each already uses both cores
for its expensive stages (the FE reference on 2 MPI ranks, the calibration on 2
workers), so two scenes side by side would only share the same two cores, double
the peak memory (the FE of one scene takes 1-9 GB) and make every timing in the
table depend on its neighbour.

``runs/corpus/corpus.json`` (rewritten atomically after every scene, so an
interrupted corpus keeps what it finished) holds per scene the mesh (vertices, tets,
min/mean edge), the exit status and ``error:`` line, the verdict of each check, the
stage times and the haptic p99; for the corpus its wall time, date, git commit and
the machine load at start and end. ``docs/corpus.md`` is its table
(:func:`corpus_markdown`; ``python -m pipelines corpus --table`` rewrites it from
``corpus.json`` alone).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import queue
import re
import signal
import subprocess
import sys
import threading
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable

import numpy as np
from forcecal.errors import DataFileError, ForcecalError
from forcecal.failures import EXIT_ERROR, describe, die_with_parent
from forcecal.h5io import atomic_path
from forcecal.provenance import git_commit
from pipelines.verdict import AT_LEAST, CHECKS as VERDICT_CHECKS, OPT_IN

KIND = "forcecal.corpus"
VERSION = 1
SCENES = Path("scenes/corpus")
OUT = Path("runs/corpus")
DOCS = Path("docs/corpus.md")
STAGE_NAMES = ("reference", "calibrate", "gravity", "report")
#: the verdict's checks every scene is judged on, in table order; the opt-in ones a report
#: holds (its scene asked for them) are appended
CHECKS = tuple(name for name in VERDICT_CHECKS if name not in OPT_IN)
#: exit statuses of ``python -m pipelines demo`` that end with a written report
#: (0: written; 3: written, verdict failed, with ``--require-pass``)
REPORT_WRITTEN = (0, 3)
#: exit statuses of a pipeline process stopped by Ctrl-C or SIGTERM: the corpus stops too
INTERRUPTED = (128 + signal.SIGINT, 128 + signal.SIGTERM)

# the pipeline's log lines this runner follows (pipelines.stages)
_STAGE_LINE = re.compile(r"^INFO pipelines\.stages: (?P<stage>\w+)\s+(?P<what>running: .*|"
                         r"done in (?P<seconds>[0-9.]+) s.*|up to date, skipped.*)$")
_ERROR_LINE = re.compile(r"^(\[rank \d+\] )?error: ")

Command = Callable[[Path, Path], list[str]]


def demo_command(scene: Path, out: Path) -> list[str]:
    """The pipeline command run for one scene."""
    return [sys.executable, "-m", "pipelines", "demo", "--scene", str(scene), "--out",
            str(out), "--no-progress"]


def mesh_summary(scene_path: Path) -> dict[str, Any]:
    """Name, mesh file and mesh statistics of one scene, read in-process (fast, no FE);
    ``{"error": ...}`` with the refusal when the scene or its mesh cannot be loaded."""
    from forcecal.problem import load_mesh
    from forcecal.scene import load_scene
    try:
        scene = load_scene(scene_path)
        mesh = load_mesh(scene)
    except ForcecalError as exc:
        return {"name": scene_path.stem, "error": describe(exc)}
    edges = mesh.edge_lengths
    return {"name": scene.name, "mesh": scene.mesh.source, "vertices": mesh.n_vertices,
            "tets": mesh.n_tets, "edge_min_m": float(edges.min()),
            "edge_mean_m": float(edges.mean())}


#: the README's "Running your own mesh" recipe (its TOML block), less what belongs to one mesh:
#: what ``--recipe`` gives every corpus scene on top of its own keys (a key both set is the
#: corpus scene's: it says what that mesh needs)
RECIPE: dict[str, Any] = {
    "experiments": ["indentation", "relaxation", "gravity_static", "gravity_dynamic", "body",
                    "second_support", "floor"],
    "test_points": {"calibration": "auto", "n_calibration": 31, "held_out": "auto",
                    "n_held_out": 8},
    "indentation": {"indenter": "punch"},
    "fe": {"element": "TH", "local_refine": 3},
    "particle": {"volume": "viscoelastic"},
    "calibration": {"method": "gradient", "global_shape": "van_gelder",
                    "body_data": "modes+loaded_modes+free_modes"},
}
#: the recipe's punch radius, in mean surface edge lengths of the mesh
RECIPE_RADIUS_EDGES = 1.5
RECIPE_OUT = Path("runs/corpus_recipe")
RECIPE_DOCS = Path("docs/corpus_recipe.md")


def recipe_scene(scene_path: Path, folder: Path) -> Path:
    """``folder/<stem>.toml``: the corpus scene ``scene_path`` with the README's own-mesh
    recipe (:data:`RECIPE`), as a user following it would write it for that mesh: its own
    keys kept (mesh, support, gravity), the punch radius :data:`RECIPE_RADIUS_EDGES` mean
    surface edge lengths of its mesh, the second support :func:`opposite_support` (hung from
    its top where it lies on a table) and the depths :func:`recipe_depths` (what the
    refusals would ask a user following the recipe to set). A scene whose mesh is refused
    is written as it is (its run ends in the same refusal, the scene's recorded result). The
    file is written only when its text changes; a scene file that cannot be loaded raises
    the :class:`ForcecalError` naming it."""
    import tomllib

    from forcecal.indenter import mean_surface_edge
    from forcecal.problem import load_mesh
    from forcecal.scene import load_scene, scene_from_dict
    from pipelines.bench.configs import scene_toml

    own = tomllib.loads(scene_path.read_text())
    scene = load_scene(scene_path)
    folder.mkdir(parents=True, exist_ok=True)  # the mesh path below is walked from it
    if scene.mesh_source_path() is not None:  # as a path from the written scene's folder
        own["mesh"] = {**own["mesh"], "source": os.path.relpath(
            scene.mesh_source_path().resolve(), folder.resolve())}
    try:
        mesh = load_mesh(scene)
    except ForcecalError:  # the scene as it is: its run is refused the same way, recorded
        data = own
    else:
        data = {"name": f"{scene.name}_recipe",
                "description": f"{scene.description} (the README's own-mesh recipe)"}
        for key, value in RECIPE.items():
            data[key] = {**value, **own.get(key, {})} if isinstance(value, dict) else value
        data.update({key: value for key, value in own.items() if key not in data})
        radius = RECIPE_RADIUS_EDGES * mean_surface_edge(mesh)
        data["indentation"].setdefault("radius", float(f"{radius:.4g}"))
        if "second_support" not in own:
            data["second_support"] = opposite_support(scene, mesh)
        recipe_depths(data, mesh, path=folder / f"{scene_path.stem}.toml")
    path = folder / f"{scene_path.stem}.toml"
    text = ("# written by python -m pipelines corpus --recipe from "
            f"{scene_path.as_posix()}: edit that scene or the recipe, not this file\n"
            + scene_toml(data))
    scene_from_dict(tomllib.loads(text), path=path)  # refused before anything is written
    if not path.is_file() or path.read_text() != text:
        with atomic_path(path) as tmp:
            tmp.write_text(text)
    return path


def opposite_support(scene: Any, mesh: Any) -> dict[str, Any]:
    """The recipe's second support: the side opposite ``[fixed]``'s on its axis, with the
    smallest tolerance [m] (at least ``[fixed]``'s, rounded up to 0.1 mm) that seats as many
    vertices as ``[fixed]`` holds."""
    from forcecal.point_selection import fixed_nodes
    fixed = scene.fixed
    held = len(fixed_nodes(mesh, fixed.axis, fixed.side, fixed.tolerance))
    side = "max" if fixed.side == "min" else "min"
    c = mesh.vertices[:, "xyz".index(fixed.axis)]
    depth = np.sort(c.max() - c if side == "max" else c - c.min())[held - 1]
    tolerance = max(fixed.tolerance, math.ceil(depth / 1e-4 - 1e-9) * 1e-4)
    return {"axis": fixed.axis, "side": side, "tolerance": float(f"{tolerance:.4g}")}


def recipe_depths(data: dict[str, Any], mesh: Any, *, path: Path) -> None:
    """Give the recipe scene ``data`` depths its mesh accepts, as the refusals ask a user to
    (a depth the corpus scene or the default sets is kept where it is accepted): below
    :data:`forcecal.problem.MAX_DEPTH_PER_EDGE` mean edge lengths, then below
    :func:`calibration.reach.accepted_depth` with the recipe's punch and test points; each
    time the largest multiple of 0.5 mm (0.1 mm below 1 mm) under the limit. A scene the
    checks refuse for another reason is left as it is (its run ends in that refusal,
    recorded)."""
    import tomllib

    from calibration.reach import accepted_depth
    from forcecal.problem import MAX_DEPTH_PER_EDGE
    from forcecal.scene import scene_from_dict
    from pipelines.bench.configs import scene_toml

    def below(limit: float) -> None:
        scene = scene_from_dict(tomllib.loads(scene_toml(data)), path=path)
        step = 5e-4 if limit > 1e-3 else 1e-4
        depth = math.ceil(limit / step - 1.0 - 1e-9) * step  # the largest multiple under it
        for section in ("indentation", "relaxation"):
            if not getattr(scene, section).depth < limit and depth > 0.0:
                data[section] = {**data.get(section, {}), "depth": float(f"{depth:.4g}")}

    try:
        below(MAX_DEPTH_PER_EDGE * float(np.mean(mesh.edge_lengths)))
        below(accepted_depth(scene_from_dict(tomllib.loads(scene_toml(data)), path=path)))
    except ForcecalError:
        return


#: seconds between the lines saying a long stage is still running
HEARTBEAT_S = 300.0


def run_scene(command: list[str], log_path: Path, echo: Callable[[str], None],
              status: Callable[[], str] = lambda: "",
              heartbeat_s: float = HEARTBEAT_S) -> dict[str, Any]:
    """Run one scene's pipeline process to its end, its output into ``log_path``.

    Echoes each stage's start and end and its ``error:`` line, and every ``heartbeat_s``
    of silence which stage is running, for how long, and ``status()`` (e.g. the FE work
    items finished so far).

    Returns ``{"exit_status", "error", "stages", "wall_time_s"}``: ``stages`` maps each
    stage to ``{"status": "ran" | "up_to_date" | "failed", "seconds"}`` as its log said
    (a stage that never started is absent), ``error`` is its last ``error:`` line."""
    stages: dict[str, dict[str, Any]] = {}
    error = None
    t0 = time.perf_counter()
    log_path.parent.mkdir(parents=True, exist_ok=True)
    with open(log_path, "w") as fh:
        fh.write(f"$ {' '.join(command)}\n")
        child = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                 text=True, bufsize=1, preexec_fn=die_with_parent)
        lines: queue.Queue = queue.Queue()
        threading.Thread(target=_read_lines, args=(child.stdout, lines), daemon=True).start()
        try:
            while (line := _next_line(lines, heartbeat_s)) is not None:
                if line == "":  # silence: say what is running
                    running = [s for s, e in stages.items() if e["status"] == "running"]
                    echo(f"{running[-1] + ' running' if running else 'starting'}, "
                         f"{(time.perf_counter() - t0) / 60:.0f} min so far{status()}")
                    continue
                fh.write(line)
                fh.flush()
                error = _follow(line.rstrip("\n"), stages, echo) or error
            exit_status = child.wait()
        finally:
            if child.poll() is None:  # the runner itself is interrupted: stop the scene too
                child.terminate()
                try:
                    child.wait(timeout=30)
                except subprocess.TimeoutExpired:
                    child.kill()
    for entry in stages.values():
        if entry["status"] == "running":
            entry["status"] = "failed"
    return {"exit_status": exit_status, "error": error, "stages": stages,
            "wall_time_s": time.perf_counter() - t0}


def _read_lines(stream, lines: queue.Queue) -> None:
    """Put every line of ``stream`` into ``lines``, then None."""
    for line in stream:
        lines.put(line)
    lines.put(None)


def _next_line(lines: queue.Queue, timeout: float) -> str | None:
    """The next line, None at the end, "" after ``timeout`` s without one."""
    try:
        return lines.get(timeout=timeout)
    except queue.Empty:
        return ""


def _follow(line: str, stages: dict[str, dict[str, Any]],
            echo: Callable[[str], None]) -> str | None:
    """Record (and echo) what one output line of the pipeline says; returns the error of an
    ``error:`` line."""
    if _ERROR_LINE.match(line):
        error = line.split("error: ", 1)[1]
        echo(f"error: {error}")
        return error
    m = _STAGE_LINE.match(line)
    if m is None:
        return None
    stage, what = m["stage"], m["what"]
    if what.startswith("running"):
        stages[stage] = {"status": "running", "seconds": None}
        echo(f"{stage} {what}")
    elif m["seconds"] is not None:
        stages[stage] = {"status": "ran", "seconds": float(m["seconds"])}
        echo(f"{stage} done in {float(m['seconds']) / 60:.1f} min")
    else:
        stages[stage] = {"status": "up_to_date", "seconds": None}
    return None


def fe_items_done(out: Path) -> str:
    """``", N FE work items finished"`` while the FE reference of ``out`` runs (its finished
    items are kept in ``reference.h5.parts/``), else ""."""
    parts = out / "reference.h5.parts"
    n = len(list(parts.glob("*.npz"))) if parts.is_dir() else 0
    return f", {n} FE work items finished" if n else ""


def _recorded_seconds(out: Path, stage: str) -> float | None:
    """Wall time of the stage run whose outputs are in ``out`` (its cache record)."""
    from pipelines.cache import Cache
    return Cache(out).elapsed(stage)


def verdict_summary(report: dict[str, Any]) -> dict[str, Any] | None:
    """``{"passed", "checks": {name: {status, calibrated, baseline, goal, reason}}}`` of a
    report, or None when it has no verdict."""
    verdict = report.get("verdict")
    if not isinstance(verdict, dict):
        return None
    checks = {name: {key: check.get(key) for key in
                     ("status", "calibrated", "baseline", "goal", "reason")}
              for name, check in (verdict.get("checks") or {}).items()}
    return {"passed": verdict.get("passed"), "checks": checks}


def scene_entry(scene_path: Path, out: Path, mesh: dict[str, Any],
                run: dict[str, Any]) -> dict[str, Any]:
    """The ``corpus.json`` entry of one scene after its run.

    Stage times: a stage that ran now, its time now; one that was up to date, the time
    recorded with its outputs (:func:`_total` for the scene's). The verdict and haptic p99
    are read from the report only when this run wrote it or found it up to date (exit
    status 0 or 3): a report left by an earlier run of other inputs is not this scene's
    result."""
    stages = run["stages"]
    for stage, entry in stages.items():
        if entry["status"] == "up_to_date":
            entry["seconds"] = _recorded_seconds(out, stage)
    entry: dict[str, Any] = {"scene": str(scene_path), **mesh,
                             "exit_status": run["exit_status"],
                             "error": run["error"] or mesh.get("error"),
                             "stages": stages,
                             "fe_time_s": stages.get("reference", {}).get("seconds"),
                             "calibration_time_s": stages.get("calibrate", {}).get("seconds"),
                             "total_time_s": _total(stages, run),
                             "run_wall_time_s": run["wall_time_s"],
                             "report": None, "verdict": None, "passed": None,
                             "haptic_p99_us": None, "missing": []}
    report_path = out / "report.json"
    if run["exit_status"] in REPORT_WRITTEN and report_path.is_file():
        report = json.loads(report_path.read_text())
        entry["report"] = str(report_path)
        entry["verdict"] = verdict_summary(report)
        if entry["verdict"] is not None:
            entry["passed"] = entry["verdict"]["passed"]
        realtime = report.get("realtime")
        if isinstance(realtime, dict):
            entry["haptic_p99_us"] = realtime.get("step_p99_us")
        entry["missing"] = [key for key in ("verdict", "realtime")
                            if not isinstance(report.get(key), dict)]
    return entry


def _total(stages: dict[str, dict[str, Any]], run: dict[str, Any]) -> float:
    """The scene's pipeline time: this run's wall time plus the recorded times of the stages
    it found up to date (for a scene run from scratch, its wall time; for one that failed,
    the time its stages took to reach the failure)."""
    return run["wall_time_s"] + sum(e["seconds"] or 0.0 for e in stages.values()
                                    if e["status"] == "up_to_date")


def read_corpus(path: str | Path) -> dict[str, Any]:
    """A ``corpus.json`` (checked for its kind)."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise DataFileError(f"cannot read {path}: {exc}") from None
    if data.get("kind") != KIND:
        raise DataFileError(f"{path} is not a corpus result (kind {data.get('kind')!r}, "
                            f"expected {KIND!r})")
    return data


def write_corpus(path: Path, data: dict[str, Any]) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=1) + "\n")


def run_corpus(scenes: Path = SCENES, out: Path = OUT, *, only: tuple[str, ...] = (),
               command: Command = demo_command, docs: Path | None = DOCS,
               echo: Callable[[str], None] = print, recipe: bool = False) -> dict[str, Any]:
    """Run every scene of ``scenes`` (or the stems in ``only``); see the module docstring.
    ``recipe``: the scenes are :func:`recipe_scene`'s (recorded in ``corpus.json``).

    Returns the corpus result, also written to ``out/corpus.json`` (and its table to
    ``docs`` unless None). With ``only``, the entries of the other scenes of ``scenes`` are
    kept from an earlier ``corpus.json`` (each entry has its own date and commit).
    """
    paths = sorted(scenes.glob("*.toml"))
    if only:
        unknown = sorted(set(only) - {p.stem for p in paths})
        if unknown:
            raise DataFileError(f"no scene {', '.join(unknown)} in {scenes}/ (scenes: "
                                f"{', '.join(p.stem for p in paths)})")
        paths = [p for p in paths if p.stem in only]
    if not paths:
        raise DataFileError(f"no scene files (*.toml) in {scenes}/")
    corpus_path = out / "corpus.json"
    earlier = {e["scene"]: e for e in (read_corpus(corpus_path)["scenes"]
                                       if corpus_path.is_file() else [])}
    meshes = {p: mesh_summary(p) for p in paths}
    # smallest first (a scene refused at load first of all): results come in soonest
    paths.sort(key=lambda p: (meshes[p].get("vertices", -1), p.stem))
    started = datetime.now(timezone.utc)
    data = {"kind": KIND, "version": VERSION, "recipe": recipe,
            "date": started.isoformat(timespec="seconds"),
            "git_commit": git_commit(), "cpus": os.cpu_count(),
            "loadavg_start": list(os.getloadavg()), "loadavg_end": None,
            "wall_time_s": None, "scenes_time_s": None, "passed": None, "scenes": []}
    kept = {str(p) for p in scenes.glob("*.toml")} - {str(p) for p in paths}
    entries = {k: v for k, v in earlier.items() if k in kept}
    t0 = time.perf_counter()
    try:
        for i, path in enumerate(paths, 1):
            mesh = meshes[path]
            size = (f"{mesh['vertices']} vertices" if "vertices" in mesh
                    else "its mesh is refused")
            echo(f"[{i}/{len(paths)}] {path.stem} ({size})")
            scene_out = out / path.stem
            when = datetime.now(timezone.utc).isoformat(timespec="seconds")
            run = run_scene(command(path, scene_out), out / "logs" / f"{path.stem}.log",
                            lambda text, name=path.stem: echo(f"  {name}: {text}"),
                            lambda where=scene_out: fe_items_done(where))
            entries[str(path)] = {**scene_entry(path, scene_out, mesh, run), "date": when,
                                  "git_commit": data["git_commit"]}
            echo(f"  {path.stem}: {_outcome(entries[str(path)])}")
            _finish(data, entries, t0, corpus_path, docs)  # kept if the corpus stops later
            if run["exit_status"] in INTERRUPTED:
                raise KeyboardInterrupt
    except BaseException:
        _finish(data, entries, t0, corpus_path, docs)
        raise
    return data


def _finish(data: dict[str, Any], entries: dict[str, dict[str, Any]], t0: float,
            corpus_path: Path, docs: Path | None) -> None:
    """Bring the corpus totals up to date and write ``corpus.json`` (and the docs table)."""
    data["scenes"] = sorted(entries.values(), key=lambda e: (e.get("vertices", -1), e["scene"]))
    data["loadavg_end"] = list(os.getloadavg())
    data["wall_time_s"] = time.perf_counter() - t0
    data["scenes_time_s"] = float(sum(e["total_time_s"] for e in data["scenes"]))
    data["passed"] = all(e["passed"] is True for e in data["scenes"])
    write_corpus(corpus_path, data)
    if docs is not None:
        with atomic_path(docs) as tmp:
            tmp.write_text(corpus_markdown(data))


def _outcome(entry: dict[str, Any]) -> str:
    """One line on how a scene ended."""
    minutes = f"{entry['run_wall_time_s'] / 60:.1f} min"
    if entry["exit_status"] not in REPORT_WRITTEN:
        return f"ended with exit status {entry['exit_status']} after {minutes}"
    if entry["verdict"] is None:
        return f"report written in {minutes}; it has no verdict"
    checks = entry["verdict"]["checks"].values()
    passed = sum(c["status"] == "passed" for c in checks)
    return (f"report written in {minutes}: verdict "
            f"{'PASS' if entry['passed'] else 'FAIL'} ({passed}/{len(checks)} checks passed)")


# ------------------------------------------------------------------------------ the table

def _minutes(seconds: float | None) -> str:
    return "" if seconds is None else f"{seconds / 60:.1f}"


def _percent(value: float | None) -> str:
    return "–" if value is None else f"{100 * value:.1f}"


def _check_cell(check: dict[str, Any] | None, name: str = "") -> str:
    """``pass 3.4 / 5.2 (≤ 10) %``: status, calibrated / baseline value, goal (a check of
    at least so many g, ``carries_its_weight``: ``pass 1.00 / 1.00 (≥ 1.00) g``)."""
    if check is None:
        return "missing"
    status = {"passed": "pass", "failed": "**fail**", "not_run": "not run"}.get(
        check["status"], str(check["status"]))
    if check["calibrated"] is None and check["baseline"] is None:
        return status
    spec = VERDICT_CHECKS.get(name)
    if spec is not None and spec.direction == AT_LEAST:
        def value(v: float | None) -> str:
            return "–" if v is None else f"{v:.2f}"
        return (f"{status} {value(check['calibrated'])} / {value(check['baseline'])} "
                f"(≥ {value(check['goal'])}) {spec.unit}")
    return (f"{status} {_percent(check['calibrated'])} / {_percent(check['baseline'])} "
            f"(≤ {_percent(check['goal'])}) %")


def _cell(text: Any) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def _wall_time(data: dict[str, Any]) -> str:
    """The run's wall time, saying which scenes it ran when it ran only some (``--only``:
    the others' entries are kept from earlier runs, each with its own date and commit)."""
    ran = [e["scene"] for e in data["scenes"] if e.get("date", "") >= data["date"]]
    total = f"the scenes' pipeline times add up to {_minutes(data['scenes_time_s'])} min"
    if len(ran) == len(data["scenes"]):
        return f"corpus wall time {_minutes(data['wall_time_s'])} min ({total})"
    names = ", ".join(Path(r).stem for r in ran) or "no scene"
    return (f"this run ran {names} in {_minutes(data['wall_time_s'])} min, the other "
            f"scenes' entries are kept from earlier runs (each entry's date and commit in "
            f"corpus.json); {total}")


def corpus_markdown(data: dict[str, Any]) -> str:
    """The Markdown page of a corpus result (``docs/corpus.md``)."""
    names = list(CHECKS) + sorted({n for e in data["scenes"] if e.get("verdict")
                                   for n in e["verdict"]["checks"]} - set(CHECKS))
    load = " / ".join(" ".join(f"{x:.2f}" for x in data[k]) if data[k] else "?"
                      for k in ("loadavg_start", "loadavg_end"))
    sources = (" The meshes, their sources and licences: "
               "[`scenes/corpus/SOURCES.md`](../scenes/corpus/SOURCES.md).")
    if data.get("recipe"):
        head = ["# The corpus with the own-mesh recipe", "",
                "Each corpus scene with the README's \"Running your own mesh\" recipe (flat punch "
                "of 1.5 mean surface edge lengths, relaxing volume term, gradient fit with the "
                "FE's natural modes, a second support opposite the scene's, the discretisation "
                "floor): `pipelines.corpus.recipe_scene`. Generated by `make corpus-recipe` "
                "(`python -m pipelines corpus --recipe`) from `runs/corpus_recipe/corpus.json`; "
                "`python -m pipelines corpus --recipe --table` rewrites this page from it."
                + sources]
    else:
        head = ["# The corpus: third-party meshes through the whole pipeline", "",
                "Generated by `make corpus` (`python -m pipelines corpus`) from "
                "`runs/corpus/corpus.json`; `python -m pipelines corpus --table` rewrites this "
                "page from it." + sources]
    lines = [
        *head,
        "",
        f"Run of {data['date']} at commit `{data['git_commit']}` on {data['cpus']} cores, "
        f"load average (1/5/15 min) at start / end {load}; {_wall_time(data)}. Overall "
        f"verdict (every scene's verdict passed): {'PASS' if data['passed'] else 'FAIL'}.",
        "",
        "A check's cell: its status, the calibrated model's and the closed-form baseline's "
        "relative error, and the goal, in %. Times in minutes; haptic p99 of one 1 ms step "
        "of the calibrated model in µs.",
        "",
        "| scene | vertices | tets | edge min / mean (mm) | exit | verdict | "
        + " | ".join(f"`{n}`" for n in names)
        + " | FE | calibration | total | haptic p99 (µs) | error |",
        "|---|---:|---:|---|---:|---|" + "---|" * len(names) + "---:|---:|---:|---:|---|",
    ]
    for e in data["scenes"]:
        verdict = e.get("verdict")
        checks = verdict["checks"] if verdict else {}
        edges = (f"{1000 * e['edge_min_m']:.2f} / {1000 * e['edge_mean_m']:.2f}"
                 if "edge_min_m" in e else "")
        passed = {True: "PASS", False: "**FAIL**", None: "none"}[e.get("passed")]
        cells = [e["name"], e.get("vertices", ""), e.get("tets", ""), edges, e["exit_status"],
                 passed] + [_check_cell(checks.get(n), n) if verdict else "" for n in names]
        p99 = e.get("haptic_p99_us")
        cells += [_minutes(e.get("fe_time_s")), _minutes(e.get("calibration_time_s")),
                  _minutes(e.get("total_time_s")), "" if p99 is None else f"{p99:.0f}",
                  e.get("error") or ("" if not e.get("missing") else
                                     "report without " + ", ".join(e["missing"]))]
        lines.append("| " + " | ".join(_cell(c) for c in cells) + " |")
    return "\n".join(lines) + "\n"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``corpus`` subcommand's options (used by :mod:`pipelines.cli`)."""
    parser.add_argument("--scenes", type=Path, default=SCENES,
                        help=f"folder of the corpus's scene files (default {SCENES})")
    parser.add_argument("--out", type=Path, default=None,
                        help=f"output folder: <out>/<scene>/, <out>/corpus.json (default {OUT})")
    parser.add_argument("--only", nargs="+", default=(), metavar="SCENE",
                        help="run only these scenes (file stems); corpus.json keeps the others")
    parser.add_argument("--docs", type=Path, default=None,
                        help=f"the Markdown table written from corpus.json (default {DOCS})")
    parser.add_argument("--table", action="store_true",
                        help="only rewrite --docs from <out>/corpus.json (no run)")
    parser.add_argument("--recipe", action="store_true",
                        help="run each scene with the README's own-mesh recipe (punch, volume "
                        "term, gradient fit, whole-body data, second support, floor): the "
                        f"scenes are written to <out>/scenes/; --out defaults to {RECIPE_OUT}, "
                        f"--docs to {RECIPE_DOCS}")


def main(args: argparse.Namespace) -> int:
    """``python -m pipelines corpus``: run the corpus (exit 0 when every scene wrote its
    report, 2 when one did not), or with ``--table`` only rewrite the docs table from
    ``corpus.json``."""
    if args.out is None:
        args.out = RECIPE_OUT if args.recipe else OUT
    if args.docs is None:
        args.docs = RECIPE_DOCS if args.recipe else DOCS
    if args.table:
        data = read_corpus(args.out / "corpus.json")
        with atomic_path(args.docs) as tmp:
            tmp.write_text(corpus_markdown(data))
        print(f"wrote {args.docs} from {args.out / 'corpus.json'}")
        return 0
    scenes = args.scenes
    if args.recipe:  # the recipe's scenes, derived from the corpus's (refusals name the scene)
        scenes = args.out / "scenes"
        for path in sorted(args.scenes.glob("*.toml")):
            if not args.only or path.stem in args.only:
                recipe_scene(path, scenes)
    data = run_corpus(scenes, args.out, only=tuple(args.only), docs=args.docs,
                      recipe=args.recipe)
    ended = [e for e in data["scenes"] if e["exit_status"] not in REPORT_WRITTEN]
    print(f"corpus: {len(data['scenes']) - len(ended)}/{len(data['scenes'])} scenes wrote "
          f"their report in {data['wall_time_s'] / 60:.1f} min; verdict "
          f"{'PASS' if data['passed'] else 'FAIL'}; {args.out / 'corpus.json'}, {args.docs}")
    return EXIT_ERROR if ended else 0
