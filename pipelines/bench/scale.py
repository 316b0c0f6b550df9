"""Scale study of ``make bench``: what each stage costs as the organ mesh grows.

The generated liver at five characteristic lengths (282, 491, 866, 1,691 and
2,936 vertices; ``--quick``: smaller), each size measured in a child process of
its own so its peak memory is its own:

* ``points_s``: mesh + fixed nodes + ``"auto"`` test points (31 + 8) and their coverage;
* ``step_us``: one explicit particle step (compiled loop, gravity + arms, one
  thread, uniform parameters; :func:`pipelines.bench.particle_engine.step_throughput`);
* ``calibration_s`` / ``evaluations``: a *short* calibration (2 calibration + 8
  held-out points, global fits of 5 + 6 cost evaluations, no local tuning,
  one worker) against a synthetic reference the particle model made with the
  uniform parameters (:func:`calibration.synthetic.synthetic_reference`), so
  it measures the fit's machinery at that size, not the FE;
* FE (P2, one process): the model build and one work item of each kind
  (``indentation`` and ``relaxation`` of one test point, ``gravity_static``, and
  ``gravity_dynamic`` over :data:`DYNAMIC_STEPS` time steps, per step), each with its
  Newton profile (``fe_<kind>_profile``: solves, iterations, tangent assemblies,
  factorisations and the seconds of residual assembly, tangent assembly, factorisations
  with their first back-solve, and the other linear solves; ``FEModel.newton_profile``);
  ``fe_reference_s`` is the *estimated* serial reference of the default scene's
  39 points from them: ``build + 39 (indentation + relaxation) + static +
  (duration / fe_dt) x dynamic step``. Sizes above :data:`FE_MAX_VERTICES` run only
  the indentation item (the others are estimated from its time per step and say so); a size that takes more than :data:`SIZE_TIMEOUT_S`
  is stopped and recorded under ``failed`` (where the 2-core machine runs out);
* ``peak_rss_mb``: the child's own peak resident memory (everything above; :func:`peak_rss_mb`).

The indentation and relaxation depths are scaled to ``DEPTH_PER_EDGE`` x the
mesh's mean edge length (5 mm, the scene's, is deeper than the refusal bound of
half an edge once edges are shorter than 10 mm). Growth exponents are
least-squares slopes of log(cost) against log(vertices). ``ranks``: the
indentation item of the second size timed on one rank and, concurrently on two
ranks (one item each), as the reference distributes items: the 2-rank
throughput speed-up is ``2 t1 / t2``.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from forcecal.errors import DataFileError
from forcecal.scene import Scene, replace

log = logging.getLogger("pipelines.bench.scale")  # also when run as __main__ (a child)

LENGTHS = {False: (0.0182, 0.0142, 0.011, 0.0083, 0.0068), True: (0.04, 0.025, 0.0182, 0.011)}
# ``make bench``'s sizes (282, 491 and 1,691 vertices): a 6x range, so the exponents stay close
# to the five sizes' (the smallest sizes alone understate them: fixed costs dominate there)
HEADLINE_LENGTHS = {False: (0.0182, 0.0142, 0.0083), True: (0.04, 0.025, 0.0182)}
DEPTH_PER_EDGE = 0.25  # indentation depth / mean edge length (the default liver: 5 / 20.5 mm)
DYNAMIC_STEPS = 4  # FE dynamic time steps timed (per-step time x the scene's steps)
FE_MAX_VERTICES = 3000  # above: only the indentation item is run (the others estimated)
SIZE_TIMEOUT_S = 720.0  # a size whose child runs longer is recorded as where the machine runs out
CALIBRATION = {"static_max_evaluations": 5, "relaxation_max_evaluations": 6, "local": False,
               "workers": 1}
KEYS = ("fe_reference_s", "calibration_s", "step_us", "peak_rss_mb", "points_s")


def sized_scene(scene: Scene, length: float, mean_edge: float) -> Scene:
    """``scene`` on the generated liver of ``length``, depths scaled to its edges, 'auto' points."""
    depth = round(DEPTH_PER_EDGE * mean_edge, 5)
    return replace(scene, mesh={"source": "generate", "characteristic_length": length},
                   test_points={"calibration": "auto", "held_out": "auto"},
                   indentation={"depth": depth}, relaxation={"depth": depth})


def peak_rss_mb() -> float:
    """This process's own peak resident memory [MB]: ``VmHWM`` of ``/proc/self/status``.

    Not ``getrusage``'s ``ru_maxrss``: on Linux a child started by fork + exec inherits
    the parent's resident size at the fork as its starting maximum (exec keeps the
    high-water mark of the forked copy), so every size of the study reported at least
    the bench driver's 3.4 GB. ``ru_maxrss`` only where ``/proc`` is missing.
    """
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0  # kB
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: kB


def measure_size(scene: Scene, length: float, quick: bool, folder: Path) -> dict[str, Any]:
    """Every number of one size (run in a child process: see :func:`study`)."""
    import numba

    from calibration import calibrate
    from calibration.synthetic import synthetic_reference
    from forcecal.liver_mesh import mesh_liver
    from forcecal.problem import build_problem
    from pipelines.bench import particle_engine as pb

    numba.set_num_threads(1)
    t0 = time.perf_counter()
    mesh = mesh_liver(length)  # gmsh's time, never a kept mesh
    mesh_s = time.perf_counter() - t0
    scene = sized_scene(scene, length, float(mesh.edge_lengths.mean()))
    t0 = time.perf_counter()
    problem = build_problem(scene, mesh)
    points_s = time.perf_counter() - t0
    row: dict[str, Any] = {
        "characteristic_length_m": length, "vertices": mesh.n_vertices, "tets": mesh.n_tets,
        "connectors": len(mesh.edges), "depth_m": scene.indentation.depth,
        "mesh_s": mesh_s, "points_s": points_s,
        "coverage": problem.coverage["calibration"]}
    log.info("scale: %s, auto test points in %.2f s (coverage %.0f %%)", mesh.summary(),
             points_s, 100 * row["coverage"])

    model = pb.scene_model(scene, mesh, problem.fixed)
    steps = int(np.clip(2e7 / len(mesh.edges), 50, 2000))
    rate = pb.step_throughput(model, steps=steps, numpy_steps=2)
    row["step_us"] = 1e6 * rate["compiled_wall_s"] / steps

    # short calibration against the particle model's own curves at this size
    small = replace(scene, name=f"scale{mesh.n_vertices}",
                    test_points={"n_calibration": 2, "n_held_out": 8},
                    calibration=CALIBRATION)
    small = dataclasses.replace(small, path=folder / "scene.toml")
    synthetic_reference(small, model.params, folder / "reference.h5")
    result = calibrate(small, folder / "reference.h5", folder / "params.h5", progress=False,
                       workers=1)
    row["calibration_s"] = result.wall_time
    row["evaluations"] = result.evaluations.get("point_curves")
    row["calibration_points"] = [2, 8]

    row.update(fe_timings(scene, problem, full=quick or mesh.n_vertices <= FE_MAX_VERTICES))
    row["peak_rss_mb"] = peak_rss_mb()
    return row


def fe_timings(scene: Scene, problem, *, full: bool, items: tuple[str, ...] = ()
               ) -> dict[str, Any]:
    """Seconds of the FE model build and of one work item of each kind (module docstring)."""
    from reference_fe.model import FEModel
    from reference_fe.run import WorkItem, compute_item

    g = scene.gravity
    t0 = time.perf_counter()
    model = FEModel(problem.mesh, scene.material, scene.fe)
    out: dict[str, Any] = {"fe_build_s": time.perf_counter() - t0}
    short = dataclasses.replace(scene, gravity=dataclasses.replace(
        g, duration=DYNAMIC_STEPS * g.fe_dt, record_interval=g.fe_dt))
    kinds = items or (("indentation", "relaxation", "gravity_static", "gravity_dynamic")
                      if full else ("indentation",))
    for kind in kinds:
        point = 0 if kind in ("indentation", "relaxation") else -1
        before = model.newton_profile()
        t0 = time.perf_counter()
        compute_item(model, short, problem, WorkItem(kind, point, 0.0))
        out[f"fe_{kind}_s"] = time.perf_counter() - t0
        out[f"fe_{kind}_profile"] = {k: v - before[k] for k, v in model.newton_profile().items()}
        log.info("scale: FE %s item on %d vertices: %.1f s", kind, problem.mesh.n_vertices,
                 out[f"fe_{kind}_s"])
    if items:
        return out
    rel_steps = scene.relaxation.ramp_steps + scene.relaxation.hold_steps
    estimated = []
    if "fe_relaxation_s" not in out:  # same solves per step as the indentation
        out["fe_relaxation_s"] = out["fe_indentation_s"] * rel_steps / scene.indentation.steps
        estimated.append("relaxation")
    if "fe_gravity_static_s" not in out:  # about 2.5 Newton solves per load step, as indenting
        out["fe_gravity_static_s"] = (out["fe_indentation_s"] * scene.gravity.static_load_steps
                                      / scene.indentation.steps)
        estimated.append("gravity_static")
    if "fe_gravity_dynamic_s" in out:
        out["fe_dynamic_step_s"] = out.pop("fe_gravity_dynamic_s") / DYNAMIC_STEPS
    else:
        out["fe_dynamic_step_s"] = out["fe_indentation_s"] / scene.indentation.steps
        estimated.append("gravity_dynamic")
    n_points = scene.test_points.n_calibration + scene.test_points.n_held_out
    out["fe_reference_s"] = (out["fe_build_s"] + n_points * (out["fe_indentation_s"]
                                                             + out["fe_relaxation_s"])
                             + out["fe_gravity_static_s"]
                             + out["fe_dynamic_step_s"] * round(g.duration / g.fe_dt))
    out["fe_estimated_items"] = estimated
    return out


def rank_timing(scene: Scene, length: float) -> dict[str, Any]:
    """One indentation item per rank, all ranks at once (run under mpirun: see :func:`study`)."""
    from mpi4py import MPI

    from forcecal.liver_mesh import generate_liver
    from forcecal.problem import build_problem

    comm = MPI.COMM_WORLD
    mesh = generate_liver(length)
    scene = sized_scene(scene, length, float(mesh.edge_lengths.mean()))
    problem = build_problem(scene, mesh)
    comm.Barrier()
    t0 = time.perf_counter()
    fe_timings(scene, problem, full=False, items=("indentation",))
    wall = comm.allreduce(time.perf_counter() - t0, op=MPI.MAX)
    return {"ranks": comm.size, "vertices": mesh.n_vertices, "items": comm.size,
            "wall_s": wall}


def growth_exponent(vertices: list[int], values: list[float | None]) -> float | None:
    """Least-squares slope of log(value) against log(vertices) (None with < 2 values)."""
    pairs = [(v, y) for v, y in zip(vertices, values) if y is not None and y > 0]
    if len(pairs) < 2:
        return None
    x, y = np.log(np.array(pairs, dtype=float)).T
    return float(np.polyfit(x, y, 1)[0])


def scale_table(bench: dict[str, Any]) -> str:
    """The Markdown table of ``bench["scale"]`` (docs/benchmarks.md) with the growth exponents."""
    def cell(value: Any, fmt: str) -> str:
        return "n/a" if value is None else format(value, fmt)

    rows = ["| vertices | tets | connectors | auto points [s] (coverage) | particle step [us] "
            "| calibration, short [s] (evaluations) | FE items [s]: indentation / relaxation "
            "/ static / dynamic step | FE reference, 39 points, 1 rank (estimated) [s] "
            "| peak memory [MB] |", "|---|---|---|---|---|---|---|---|---|"]
    for r in bench["scale"]:
        estimated = "*" if r.get("fe_estimated_items") else ""
        rows.append(
            f"| {r['vertices']} | {r['tets']} | {r['connectors']} | {r['points_s']:.2f} "
            f"({100 * r['coverage']:.0f} %) | {r['step_us']:.1f} | {r['calibration_s']:.0f} "
            f"({r['evaluations']}) | {cell(r.get('fe_indentation_s'), '.1f')} / "
            f"{cell(r.get('fe_relaxation_s'), '.1f')}{estimated} / "
            f"{cell(r.get('fe_gravity_static_s'), '.1f')} / "
            f"{cell(r.get('fe_dynamic_step_s'), '.2f')}{estimated} | "
            f"{cell(r.get('fe_reference_s'), '.0f')} | {r['peak_rss_mb']:.0f} |")
    exp = bench["scale_study"]["exponents"]
    rows.append(f"| growth exponent | | | {cell(exp.get('points_s'), '.2f')} | "
                f"{cell(exp.get('step_us'), '.2f')} | {cell(exp.get('calibration_s'), '.2f')} | "
                f"{cell(exp.get('fe_indentation_s'), '.2f')} (indentation) | "
                f"{cell(exp.get('fe_reference_s'), '.2f')} | "
                f"{cell(exp.get('peak_rss_mb'), '.2f')} |")
    return "\n".join(rows)


def scale_section(bench: dict[str, Any]) -> list[str]:
    """BENCH.md's lines of the scale study (table, failed sizes, ranks, method)."""
    study_ = bench["scale_study"]
    lines = ["", "## Scale (generated liver)", "", scale_table(bench), "",
             "`*`: estimated from the indentation's time per step (FE items skipped at that "
             "size)."]
    for f in study_["failed"]:
        lines.append(f"- {f}")
    runs = study_["ranks"]["runs"]
    if len(runs) < 2:
        return lines
    lines += ["", f"One FE indentation item on {runs[0]['vertices']} vertices: "
              f"{runs[0]['wall_s']:.1f} s on 1 rank; 2 ranks computing one item each at once: "
              f"{runs[1]['wall_s']:.1f} s (throughput speed-up "
              f"{study_['ranks']['speedup_2ranks']:.2f} of 2). Load averages (1, 5, 15 min) "
              f"before and after each size: {study_['load_average']}.", ""]
    return lines


def _child(args: list[str], cwd: Path, mpi_ranks: int = 0) -> dict[str, Any]:
    """Run this module in a child process (under mpirun with ``mpi_ranks``); its JSON row."""
    import signal

    from pipelines.runners.reference import mpirun_environment

    cmd = [sys.executable, "-m", "pipelines.bench.scale", *args]
    env = os.environ.copy()
    if mpi_ranks:
        cmd = [shutil.which("mpirun") or "mpirun", "-n", str(mpi_ranks), *cmd]
        env = mpirun_environment()
    child = subprocess.Popen(cmd, cwd=cwd, env=env, stdin=subprocess.DEVNULL,
                             stdout=subprocess.PIPE, start_new_session=True)
    try:
        stdout, _ = child.communicate(timeout=SIZE_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        os.killpg(child.pid, signal.SIGKILL)  # the child's own session: it and its ranks
        child.communicate()
        raise DataFileError(f"scale study: {' '.join(args)} did not finish within "
                            f"{SIZE_TIMEOUT_S:g} s (stopped)") from None
    lines = [line for line in stdout.decode().splitlines() if line.startswith("{")]
    if child.returncode != 0 or not lines:
        raise DataFileError(f"scale study: {' '.join(args)} failed (exit code "
                            f"{child.returncode}; its message is above)")
    return json.loads(lines[0])


def study(scene: Scene, cache: Path, quick: bool, lengths: tuple[float, ...] | None = None,
          rank_timing: bool = True) -> dict[str, Any]:
    """The ``scale`` key of bench.json: one row per size of ``lengths`` (default
    :data:`LENGTHS`), growth exponents, 1 vs 2 ranks (unless not ``rank_timing``)."""
    root = Path(__file__).resolve().parents[2]
    scene_path = str(scene.path)
    rows, failed, ranks = [], [], []
    load = [list(os.getloadavg())]

    def size(length: float) -> None:
        with tempfile.TemporaryDirectory(dir=cache if cache.is_dir() else None) as tmp:
            args = ["--scene", scene_path, "--length", str(length), "--folder", tmp]
            for attempt in (1, 2):  # once more if it failed (not timed out): on a crowded
                try:                # machine a child may fail to start MPI (MPI_Init_thread)
                    rows.append(_child(args + (["--quick"] if quick else []), root))
                    break
                except DataFileError as exc:  # where the machine runs out: recorded, not fatal
                    log.warning("%s", exc)
                    if attempt == 2 or "did not finish" in str(exc):
                        failed.append({"characteristic_length_m": length, "failed": str(exc)})
                        break
        load.append(list(os.getloadavg()))

    for length in lengths or LENGTHS[quick]:
        size(length)
    for k in (1, 2) if rank_timing else ():
        try:
            ranks.append(_child(["--scene", scene_path, "--length", str(LENGTHS[quick][1]),
                                 "--ranks-item"], root, mpi_ranks=k))
        except DataFileError as exc:
            log.warning("%s", exc)
            failed.append({"ranks": k, "failed": str(exc)})
    vertices = [r["vertices"] for r in rows]
    return {"scale": rows,
            "scale_study": {
                "exponents": {k: growth_exponent(vertices, [r.get(k) for r in rows])
                              for k in (*KEYS, "fe_indentation_s", "fe_build_s")},
                "failed": failed,
                "ranks": {"runs": ranks, "speedup_2ranks": (
                    2 * ranks[0]["wall_s"] / ranks[1]["wall_s"] if len(ranks) == 2 else None)},
                "load_average": load,
                "method": __doc__.split("\n\n", 1)[1].strip()}}


def whole_reference(scene: Scene, cache: Path, quick: bool) -> dict[str, Any]:
    """The ``scale_reference`` key of bench.json: the FE reference of the scene's test points
    on the largest size of :data:`LENGTHS` (2,936 vertices; ``quick``: 866), computed as a
    whole run on 2 MPI ranks and timed (the study's other FE numbers are single items), with
    the date and the load averages before and after."""
    from forcecal.liver_mesh import generate_liver
    from pipelines.bench.configs import derived_scene
    from pipelines.bench.items import measure_reference, now_utc

    length = LENGTHS[quick][-1]
    mesh = generate_liver(length)
    sized = sized_scene(scene, length, float(mesh.edge_lengths.mean()))
    changes = {"mesh": {"source": "generate", "characteristic_length": length},
               "test_points": {"calibration": "auto", "held_out": "auto"},
               "indentation": {"depth": sized.indentation.depth},
               "relaxation": {"depth": sized.relaxation.depth}}
    folder = cache / "scale-reference"
    derived = derived_scene(scene, f"scale{mesh.n_vertices}", changes, folder)
    load = [list(os.getloadavg())]
    started = now_utc()
    wall = measure_reference(derived, 2, folder, progress=False)
    load.append(list(os.getloadavg()))
    return {"scale_reference": {"vertices": mesh.n_vertices, "ranks": 2, "wall_s": wall,
                                "measured": started, "load_average": load,
                                "depth_m": sized.indentation.depth}}


def headline_study(scene: Scene, cache: Path, quick: bool) -> dict[str, Any]:
    """``make bench``'s scale study: the sizes of :data:`HEADLINE_LENGTHS`, no rank timing."""
    return study(scene, cache, quick, HEADLINE_LENGTHS[quick], rank_timing=False)


def main(argv: list[str] | None = None) -> int:
    import argparse

    from forcecal.logs import configure_logging
    from forcecal.scene import load_scene

    parser = argparse.ArgumentParser(description="one size of the scale study (JSON on stdout)")
    parser.add_argument("--scene", required=True)
    parser.add_argument("--length", type=float, required=True)
    parser.add_argument("--folder", default=None)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--ranks-item", action="store_true")
    parser.add_argument("--table", action="store_true",
                        help="print the Markdown table of the bench.json at --scene instead")
    args = parser.parse_args(argv)
    # MPI first, while the process is small: Open MPI's singleton start forks a helper, which
    # failed here ("system limit on number of children") once the calibration had run
    from mpi4py import MPI  # noqa: F401
    if args.table:
        print(scale_table(json.loads(Path(args.scene).read_text())))
        return 0
    configure_logging(logging.INFO)
    scene = load_scene(args.scene)
    if args.ranks_item:
        row = rank_timing(scene, args.length)
        from mpi4py import MPI
        if MPI.COMM_WORLD.rank != 0:
            return 0
    else:
        row = measure_size(scene, args.length, args.quick, Path(args.folder))
    print(json.dumps(row), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
