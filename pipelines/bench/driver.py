"""``make bench`` and ``make bench-full``: speed and error of forcecal on this machine.

``python -m pipelines bench [--full] [--quick] [--out DIR] [--scene FILE] [--ranks K]
[--no-progress] [--only ITEMS | --cold]``
writes ``DIR/bench.json`` (keys below), ``DIR/pareto.png`` and ``DIR/BENCH.md``.
Without ``--full`` (``make bench``, ``DIR`` = ``runs/bench-headline``) it runs the headline
items of :data:`HEADLINE`, some of them reduced (:data:`REDUCED`), within about a quarter of
an hour on two idle cores; ``--full`` (``make bench-full``, ``DIR`` = ``runs/bench``, the
committed one) runs every item at full size. ``--quick`` benchmarks ``scenes/tiny.toml``
with small sizes (development, a few minutes; ``DIR`` = ``runs/bench-quick``); the default
is the default liver. ``bench.json`` records which (``selection``: "headline" or "full").

Items, in order (each logs ``bench [k/N] <item>`` and its time):

1. ``default pipeline run``: the default scene through the cached pipeline in
   ``DIR/cache/runs/default/`` (seeded from ``runs/<scene name>/`` when that
   folder holds a finished run, so ``make demo``'s work is reused);
2. ``run time vs error``: the configurations of :mod:`pipelines.bench.configs` (cached
   pipelines; the headline runs fewer settings per axis), the particle time-step sweep and
   the FE discretisation study;
3. ``reference timings``: wall time of the full default reference with 2 MPI ranks (the
   default run's own: its ``reference.h5`` records wall time and rank count) and, in the full
   bench, with 1 rank: one run kept in ``DIR/cache/reference_timing.json`` for the same code
   and scene fingerprints (a cold full bench therefore computes a full reference once more);
4. ``particle engine`` (:mod:`pipelines.bench.particle_engine`): ``kernel`` throughput
   (compiled vs numpy step, default liver and a >= 10k-connector liver), ``gravity_dynamic``
   (3 s of the calibrated model, against the FE's time and error), ``skip`` (the same runs
   with and without the terms they do not need), haptic latency, evaluator times;
5. ``stability limits``: estimated vs empirical stability limits
   (:mod:`pipelines.bench.stability`);
6. every item of :data:`STUDIES` (one module each).

Investigations that answered one question once (cross-validation of calibration settings,
the sag and release studies, the contact size) are no items: they live in the top-level
``studies`` package, each with its own command (``docs/studies.md``).

``--only ITEM[,ITEM]`` runs only those items and keeps the other keys of the
``bench.json`` already in the folder (each item records its own time in ``item_s``),
``machine`` included: that stays the last whole run's, and the partial run's machine,
date and commit are appended to ``reruns`` with the items it ran (an item rerun again
leaves the earlier entry). The folder's run must be of the same selection, scene and size.

Cold times: an item that reused nothing computed earlier (no cached pipeline stage,
FE study or reference timing, see :data:`REUSE_MESSAGES`) records its time in
``item_s_cold`` too; one that reused something keeps the cold time of the run that
computed what it reused (the earlier ``bench.json``'s of the same selection, None if
unknown). ``wall_s_cold`` is their sum: what the bench takes with nothing cached.
``--cold`` measures it directly: it needs an empty ``DIR/cache`` (refused otherwise),
marks it cold (:func:`pipelines.bench.items.runs_source`: nothing is adopted from
``runs/``), runs every item of the selection, and records every item's time as its cold
time and ``wall_s_cold`` = ``wall_s``. Work one item reuses from an earlier item of the
same run (the default pipeline run's reference in the experiments and calibration-methods
items) is counted once, in the item that computed it.

Fixed keys of ``bench.json``: ``kernel {connectors, updates_per_s, numpy_ratio}``,
``gravity_dynamic {particle_s, fe_s, speedup, error}``, ``calibration {wall_s,
evaluations}``, ``reference {wall_s_1rank, wall_s_2ranks}`` (``wall_s_1rank`` null in the
headline, which does not time the 1-rank reference), ``pareto [{config, stage, wall_s,
errors}]``, ``skip [{scene, full_s, skipped_s}]``; the rest (``machine``, ``haptic``,
``evaluators``, ``stability``, ...) are extras. Numbers are from real runs of this code;
timings on a shared machine are indicative (``machine.load_average_start`` says how busy
it was).
"""

from __future__ import annotations

import argparse
import importlib
import json
import logging
import os
import platform
import re
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from forcecal.errors import DataFileError, ForcecalError
from forcecal.h5io import atomic_path
from forcecal.provenance import git_commit
from forcecal.scene import load_scene
from pipelines.bench import configs as bc
from pipelines.bench.report import selection
from pipelines.bench.items import (COLD_MARKER, GOALS, PAPER, ROOT, calibration_item,
                                   default_run, dt_sweep, fe_rows, now_utc, particle_items,
                                   reference_timings)

log = logging.getLogger(__name__)

DT_FRACTIONS = {False: (0.1, 0.25, 0.5, 0.75, 1.0), True: (0.25, 0.5, 1.0)}


#: the first five items (module docstring), in order
BUILT_IN = ("default pipeline run", "run time vs error", "reference timings", "particle engine",
            "stability limits")
# Items after those five: item name -> "module:function", a function study(scene, cache
# folder, quick) -> the bench.json keys it owns. Each lives in a module of its own (imported
# only when it runs), so adding an item adds one line here.
STUDIES: dict[str, str] = {
    "experiments": "pipelines.bench.experiments:study",
    "haptic scale": "pipelines.bench.haptic:study",
    "fe_convergence": "pipelines.bench.fe_convergence:study",
    "scale": "pipelines.bench.scale:study",
    "calibration methods": "pipelines.bench.calibration_methods:study",
    "volume term": "pipelines.bench.volume:study",
}
#: the items of ``make bench`` (``make bench-full`` runs every item): the headline axes, speed
#: (kernel, haptic, stability) and error (run time vs error on the default scene, FE
#: convergence, scale with its growth exponents). Left to the full bench: the 1-rank
#: reference timing, ``experiments`` (a reference and a calibration per experiment list) and
#: ``calibration methods`` (eight pipelines on two scenes).
HEADLINE = ("default pipeline run", "run time vs error", "reference timings", "particle engine",
            "stability limits", "haptic scale", "fe_convergence", "scale", "volume term")
#: the headline's reduced versions of studies: item name -> "module:function" (same signature
#: as the full one in :data:`STUDIES`). The built-in items "run time vs error" (fewer settings
#: per axis, :func:`pipelines.bench.configs.configs`) and "reference timings" (2 ranks only)
#: are reduced by the driver's ``full`` flag.
HEADLINE_STUDIES = {"fe_convergence": "pipelines.bench.fe_convergence:headline_study",
                    "scale": "pipelines.bench.scale:headline_study"}
# log messages (regular expressions) by which a cache hit announces itself: an item that logs
# one reused earlier work, so its time is not a cold time
REUSE_MESSAGES = re.compile(r"bench: reusing |up to date, skipped|already holds .* not "
                            r"recomputed|adopting the existing|resuming from checkpoint")
# items that need the default pipeline run (its folder is in ``state["default"]``)
NEEDS_DEFAULT = {"run time vs error", "reference timings", "particle engine", "experiments",
                 "calibration methods"}


# the fixed keys of bench.json, checked before it is written
BENCH_KEYS = {"kernel": ("connectors", "updates_per_s", "numpy_ratio"),
              "gravity_dynamic": ("particle_s", "fe_s", "speedup", "error"),
              "calibration": ("wall_s", "evaluations"),
              "reference": ("wall_s_1rank", "wall_s_2ranks")}
ROW_KEYS = {"pareto": ("config", "stage", "wall_s", "errors"),
            "skip": ("scene", "full_s", "skipped_s")}


def check_bench(bench: dict[str, Any]) -> None:
    """Raise :class:`DataFileError` if a fixed key of ``bench.json`` is missing or one of its
    numbers is not finite (a failed Pareto configuration may have ``wall_s`` None: it says
    why under ``failed``; the headline's ``reference.wall_s_1rank`` is None: not timed)."""
    optional = {("gravity_dynamic", "error")}  # None only when the gravity stage failed
    if selection(bench) == "headline":
        optional.add(("reference", "wall_s_1rank"))

    def number(where: str, value: Any, allow_none: bool = False) -> None:
        if value is None and allow_none:
            return
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(
                value):
            raise DataFileError(f"bench.json: {where} = {value!r} is not a finite number")

    for group, keys in BENCH_KEYS.items():
        for k in keys:
            if k not in bench.get(group, {}):
                raise DataFileError(f"bench.json: {group}.{k} is missing")
            number(f"{group}.{k}", bench[group][k], allow_none=(group, k) in optional)
    for group, keys in ROW_KEYS.items():
        rows = bench.get(group)
        if not isinstance(rows, list) or not rows:
            raise DataFileError(f"bench.json: {group} must be a non-empty list of rows")
        for n, row in enumerate(rows):
            for k in keys:
                if k not in row:
                    raise DataFileError(f"bench.json: {group}[{n}].{k} is missing")
            for k in keys[1:] if group == "skip" else ("wall_s",):
                number(f"{group}[{n}].{k}", row[k], allow_none="failed" in row)


def selection_items(full: bool) -> tuple[str, ...]:
    """The items a whole run of ``make bench-full`` (``full``) or ``make bench`` runs, in
    order."""
    every = BUILT_IN + tuple(STUDIES)
    return every if full else tuple(name for name in every if name in HEADLINE)


def read_bench(path: str | Path) -> dict[str, Any]:
    """A ``bench.json`` with its fixed keys checked (:func:`check_bench`)."""
    try:
        bench = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise DataFileError(f"cannot read {path}: {exc}") from exc
    if not isinstance(bench, dict):
        raise DataFileError(f"{path}: not a bench.json (a JSON object is expected)")
    check_bench(bench)
    return bench


# ---------------------------------------------------------------------------- default run

# ---------------------------------------------------------------------------- driver

def cpu() -> dict[str, Any]:
    """The CPU's model name and widest SIMD extension (Linux ``/proc/cpuinfo``; None
    elsewhere). Two-core machines differ: the unchanged particle kernels measured 2-3x
    slower on the AMD EPYC (AVX2) of the 2026-12-03 cold run than in the 2026-12-02 run,
    whose CPU was not recorded."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return {"cpu_model": None, "simd": None}
    model = re.search(r"^model name\s*:\s*(.+)$", text, re.M)
    listed = re.search(r"^flags\s*:\s*(.+)$", text, re.M)
    flags = set(listed.group(1).split()) if listed else set()
    simd = next((f for f in ("avx512f", "avx2", "avx", "sse4_2") if f in flags), None)
    return {"cpu_model": model.group(1).strip() if model else None, "simd": simd}


def machine() -> dict[str, Any]:
    """Where and when: CPU, count, load, platform, commit (benchmarks need an idle machine)."""
    return {"date": now_utc(), **cpu(), "cpu_count": os.cpu_count(),
            "platform": platform.platform(), "python": platform.python_version(),
            "load_average_start": list(os.getloadavg()), "git_commit": git_commit(ROOT)}


class ReuseCounter(logging.Handler):
    """Counts the log records of the project that announce a cache hit (:data:`REUSE_MESSAGES`)."""

    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.hits = 0

    def emit(self, record: logging.LogRecord) -> None:
        if REUSE_MESSAGES.search(record.getMessage()):
            self.hits += 1


def cold_times(item_s: dict[str, float], reused: set[str], previous: dict[str, Any]
               ) -> dict[str, float | None]:
    """Each item's cold time [s]: its own ``item_s`` when it reused nothing, else the earlier
    run's ``item_s_cold`` (``previous``, a bench.json or {}), None if that run had none."""
    earlier = previous.get("item_s_cold", {})
    return {name: (earlier.get(name) if name in reused else seconds)
            for name, seconds in item_s.items()}


def selected_items(names: list[str], only: tuple[str, ...]) -> tuple[str, ...]:
    """The items an ``--only`` run runs, in the bench's order: ``only`` and the default
    pipeline run when one of them needs it (:data:`NEEDS_DEFAULT`). All of them are
    recorded in ``reruns``: the default run rewrites its keys (the calibration block,
    goals) too."""
    keep = {"default pipeline run"} if set(only) & NEEDS_DEFAULT else set()
    return tuple(name for name in names if name in set(only) | keep)


def whole_run(out: Path, scene: str, quick: bool, full: bool = True) -> dict[str, Any]:
    """The ``bench.json`` in ``out`` that an ``--only`` run completes, read and checked
    (:func:`read_bench`) before the run runs anything: refused when there is none (its other
    keys would be missing) or when it is of another scene, size or selection (the keys would
    mix two benches)."""
    path = out / "bench.json"
    if not path.is_file():
        raise ForcecalError(f"bench --only: {path} does not exist; --only reruns items of a "
                            f"whole bench run in that folder and keeps its other keys: run "
                            f"the whole bench there first")
    previous = read_bench(path)
    size = {True: "--quick", False: "full"}
    earlier = (previous.get("scene"), bool(previous.get("quick")))
    if earlier != (scene, quick):
        raise ForcecalError(f"bench --only: {path} is a {size[earlier[1]]} run of scene "
                            f"{earlier[0]!r}, this one a {size[quick]} run of {scene!r}: pass "
                            f"the same scene and --quick, or another --out")
    wanted = "full" if full else "headline"
    if selection(previous) != wanted:
        raise ForcecalError(f"bench --only: {path} is a {selection(previous)} run, this one a "
                            f"{wanted} run: {'drop' if full else 'pass'} --full, or pass "
                            f"another --out")
    return previous


def partial_bench(previous: dict[str, Any], this_machine: dict[str, Any],
                  only: tuple[str, ...], scene: str, quick: bool, full: bool = True
                  ) -> dict[str, Any]:
    """The start of an ``--only`` run's bench.json: every key of the last run in the folder
    (``previous``), its ``machine`` included, and this run's machine, date and commit
    appended to ``reruns`` with the items it runs (module docstring)."""
    earlier = [{**r, "items": [i for i in r["items"] if i not in only]}
               for r in previous.get("reruns", []) if set(r["items"]) - set(only)]
    return {**previous, "scene": scene, "quick": quick,
            "selection": "full" if full else "headline",
            "machine": previous.get("machine", this_machine),
            "reruns": earlier + [{"items": list(only), **this_machine}]}


def run_bench(out: Path, *, full: bool = False, quick: bool = False,
              scene_path: Path | None = None, ranks: int = 2, progress: bool = True,
              only: tuple[str, ...] = (), cold: bool = False) -> dict[str, Any]:
    """The items of ``make bench`` (:data:`HEADLINE`, some reduced) or, ``full``, of
    ``make bench-full`` (every item of the module docstring, then every study of
    :data:`STUDIES`); writes bench.json, pareto.png, BENCH.md in ``out``.

    ``only`` names the items to run (their keys replace those of the ``bench.json``
    already in ``out``, the rest are kept as they are; the default pipeline run is
    brought up to date first when an item needs it). ``cold``: measure the cold wall time
    (module docstring); needs an empty ``out/cache`` and no ``only``.
    """
    from pipelines.bench.report import write_markdown, write_pareto_plot
    from pipelines.bench.stability import stability_table

    scene = load_scene(scene_path or ROOT / "scenes" / ("tiny.toml" if quick else "liver.toml"))
    cache = out / "cache"
    runs = cache / "runs"
    if cold:
        if only:
            raise ForcecalError("bench: --cold runs every item; it cannot be combined with --only")
        if cache.is_dir() and any(cache.iterdir()):
            raise ForcecalError(f"bench --cold: {cache} holds earlier work; remove it (or pass "
                                f"another --out) to time a cold run")
        cache.mkdir(parents=True, exist_ok=True)
        (cache / COLD_MARKER).write_text("started cold: adopts nothing from runs/\n")
    elif (cache / COLD_MARKER).is_file():  # a warm run may seed from runs/ again
        (cache / COLD_MARKER).unlink()
    bench: dict[str, Any] = {"machine": machine(), "scene": scene.name, "quick": quick,
                             "selection": "full" if full else "headline"}
    state: dict[str, Any] = {}
    # the last run's cold times, if it ran the same items (an --only run reads and checks it
    # below: whole_run)
    previous = json.loads((out / "bench.json").read_text()) if (
        not only and (out / "bench.json").is_file()) else {}
    if previous and (selection(previous), previous.get("scene"), bool(previous.get(
            "quick"))) != (bench["selection"], scene.name, quick):
        previous = {}

    def default_item():
        state["default"], state["row"] = default_run(scene, cache, ranks=ranks,
                                                     progress=progress)
        bench["calibration"] = calibration_item(state["default"])

    def pareto_item():
        rows = [bc.default_row(state["row"], scene)]
        rows += bc.axis_defaults(scene, rows[0])
        for config in bc.configs(scene, quick, full):
            log.info("bench: configuration %s / %s", config.axis, config.label)
            rows.append(bc.run_config(config, scene, state["default"], runs, ranks=ranks,
                                      progress=progress))
        rows += dt_sweep(scene, state["default"], DT_FRACTIONS[quick])
        rows += fe_rows(scene, cache, ranks)
        bc.mark_fronts(rows)
        bench["pareto"] = rows

    def reference_item():
        bench["reference"] = reference_timings(scene, state["default"], cache, progress,
                                               ranks=(1, 2) if full else (2,))

    def particle_item():
        keys = particle_items(scene, state["default"], quick)
        keys["skip"] += [r for r in bench.get("skip", []) if "study" in r]  # the studies' rows
        bench.update(keys)

    def stability_item():
        bench["stability"] = stability_table(quick)

    def study_item(name: str) -> Callable[[], None]:
        target = STUDIES[name] if full else HEADLINE_STUDIES.get(name, STUDIES[name])

        def run() -> None:
            module, function = target.split(":")
            keys = getattr(importlib.import_module(module), function)(scene, cache, quick)
            for k, rows in keys.items():
                if k in ROW_KEYS:  # a shared list of rows: the study's replace its earlier ones
                    rows = [r for r in bench.get(k, []) if r.get("study") != name] + [
                        {**r, "study": name} for r in rows]
                bench[k] = rows
        return run

    built_in = dict(zip(BUILT_IN, (default_item, pareto_item, reference_item, particle_item,
                                   stability_item)))
    items = [(name, built_in[name] if name in built_in else study_item(name))
             for name in selection_items(True)]
    if only:
        unknown = sorted(set(only) - {name for name, _ in items})
        if unknown:
            raise ForcecalError(f"bench --only: unknown item(s) {unknown}; known: "
                                f"{[name for name, _ in items]}")
        full_only = sorted(set(only) - set(selection_items(full)))
        if full_only:
            raise ForcecalError(f"bench --only: {full_only} run in make bench-full only: pass "
                                "--full (and its folder, runs/bench by default)")
        previous = whole_run(out, scene.name, quick, full)
        run = selected_items([name for name, _ in items], only)
        items = [(name, fn) for name, fn in items if name in run]
        bench = partial_bench(previous, bench["machine"], run, scene.name, quick, full)
    else:
        items = [(name, fn) for name, fn in items if name in selection_items(full)]
    bench["item_s"] = dict(bench.get("item_s", {}))
    reused: set[str] = set()
    start = time.perf_counter()
    for k, (name, fn) in enumerate(items, 1):
        log.info("bench [%d/%d] %s ...", k, len(items), name)
        counter = ReuseCounter()
        logging.getLogger().addHandler(counter)
        t0 = time.perf_counter()
        try:
            fn()
        finally:
            logging.getLogger().removeHandler(counter)
        bench["item_s"][name] = time.perf_counter() - t0
        if counter.hits:
            reused.add(name)
        log.info("bench [%d/%d] %s done in %.1f s%s", k, len(items), name,
                 bench["item_s"][name], " (reused earlier work)" if counter.hits else "")
    if not only:  # a partial run keeps the full run's wall time
        bench["wall_s"] = time.perf_counter() - start
    if cold:  # everything was computed in this run (reuse between its items included)
        bench["item_s_cold"] = dict(bench["item_s"])
    else:  # a partial run keeps the other items' cold times
        bench["item_s_cold"] = {**(previous.get("item_s_cold", {}) if only else {}),
                                **cold_times({n: bench["item_s"][n] for n, _ in items},
                                             reused, previous)}
    cold = list(bench["item_s_cold"].values())
    bench["wall_s_cold"] = (None if None in cold or set(bench["item_s_cold"]) != set(
        bench["item_s"]) else float(sum(cold)))
    (bench["reruns"][-1] if only else bench["machine"])["load_average_end"] = list(
        os.getloadavg())
    bench["goals"], bench["paper"] = GOALS, PAPER
    check_bench(bench)
    with atomic_path(out / "bench.json") as tmp:
        tmp.write_text(json.dumps(bench, indent=1) + "\n")
    write_pareto_plot(out / "pareto.png", bench)
    write_markdown(out / "BENCH.md", bench)
    log.info("bench: wrote %s, %s, %s", out / "bench.json", out / "pareto.png", out / "BENCH.md")
    return bench


def default_out(full: bool, quick: bool) -> Path:
    """Where a run writes unless told: ``runs/bench`` (``make bench-full``, committed),
    ``runs/bench-headline`` (``make bench``), ``runs/bench-quick[-full]`` with ``--quick``."""
    if quick:
        return Path("runs/bench-quick-full" if full else "runs/bench-quick")
    return Path("runs/bench" if full else "runs/bench-headline")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``bench`` subcommand's options (used by :mod:`pipelines.cli`)."""
    parser.add_argument("--full", action="store_true",
                        help="every item at full size (make bench-full; about 1.5-2 h cold); "
                             "default: the headline items (make bench; about 15 min cold)")
    parser.add_argument("--out", default=None,
                        help="output folder (default: runs/bench-headline; runs/bench with "
                             "--full; runs/bench-quick[-full] with --quick)")
    parser.add_argument("--quick", action="store_true",
                        help="small sizes on scenes/tiny.toml (a few minutes)")
    parser.add_argument("--scene", default=None, help="scene to benchmark (default: the liver)")
    parser.add_argument("--ranks", type=int, default=2, help="MPI ranks of FE references")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    parser.add_argument("--only", default="",
                        help="comma-separated items to run (e.g. 'stability limits'); the other "
                             "keys of DIR/bench.json are kept")
    parser.add_argument("--cold", action="store_true",
                        help="time a cold run: needs an empty DIR/cache, adopts nothing from "
                             "runs/, records wall_s_cold")


def main(args: argparse.Namespace) -> int:
    """Run the benchmark from parsed ``args`` (see :func:`add_arguments`)."""
    out = Path(args.out) if args.out else default_out(args.full, args.quick)
    run_bench(out, full=args.full, quick=args.quick, scene_path=Path(args.scene) if args.scene else None,
              ranks=args.ranks, progress=not args.no_progress,
              only=tuple(name.strip() for name in args.only.split(",") if name.strip()),
              cold=args.cold)
    print(f"bench: outputs in {out}/ (bench.json, pareto.png, BENCH.md)")
    return 0
