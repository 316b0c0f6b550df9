"""``make bench`` and ``make bench-full``: speed and error of forcecal on this machine.

``python -m pipelines bench [--full] [--quick] [--out DIR] [--scene FILE] [--ranks K]
[--no-progress] [--only ITEMS | --cold]``
writes ``DIR/bench.json`` (keys below), ``DIR/pareto.png`` and ``DIR/BENCH.md``.
Without ``--full`` (``make bench``, ``DIR`` = ``runs/bench-headline``) it runs the headline
items, some of them reduced, within about a quarter of an hour on two idle cores; ``--full``
(``make bench-full``, ``DIR`` = ``runs/bench``, the committed one) runs every item at full
size. Which items each runs, and at what size, is the table :data:`ITEMS`. ``--quick``
benchmarks ``scenes/tiny.toml`` with small sizes (development, a few minutes; ``DIR`` =
``runs/bench-quick``); the default is the default liver. ``bench.json`` records which
(``selection``: "headline" or "full").

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
6. the items in modules of their own (:class:`ModuleItem`): ``experiments`` (full bench
   only), ``haptic scale``, ``fe_convergence``, ``scale``, ``scale reference`` (full bench
   only: the whole FE reference on the study's largest mesh, 2 ranks), ``calibration
   methods`` (full bench only), ``volume term``, ``discretisation floor`` (full bench only:
   the gravity test of a vertex-dof FE model on the particle mesh, :mod:`pipelines.bench.floor`).

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
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any, Callable

import numpy as np

from forcecal.errors import DataFileError, ForcecalError
from forcecal.h5io import atomic_path
from forcecal.provenance import git_commit
from forcecal.scene import Scene, load_scene
from pipelines.bench import configs as bc
from pipelines.bench.report import selection
from pipelines.bench.items import (COLD_MARKER, GOALS, PAPER, ROOT, calibration_item,
                                   default_run, dt_sweep, fe_rows, now_utc, particle_items,
                                   reference_timings)

log = logging.getLogger(__name__)

DT_FRACTIONS = {False: (0.1, 0.25, 0.5, 0.75, 1.0), True: (0.25, 0.5, 1.0)}


# ---------------------------------------------------------------------------- items

@dataclass
class BenchRun:
    """What the items of one bench run share: the benchmarked scene, the cache folder,
    ``--quick``, the MPI ranks of FE references, progress bars, and the default pipeline
    run's folder and Pareto row once its item ran (the items of :data:`ITEMS` that
    ``needs_default`` read them)."""
    scene: Scene
    cache: Path
    quick: bool
    ranks: int = 2
    progress: bool = True
    default: Path | None = None
    default_row: dict[str, Any] | None = None


def default_pipeline_run(run: BenchRun) -> dict[str, Any]:
    """The default scene through the cached pipeline (module docstring, item 1)."""
    run.default, run.default_row = default_run(run.scene, run.cache, ranks=run.ranks,
                                               progress=run.progress)
    return {"calibration": calibration_item(run.default)}


def run_time_vs_error(run: BenchRun, full: bool) -> dict[str, Any]:
    """The Pareto rows: the default, every configuration of
    :func:`pipelines.bench.configs.configs` (``full`` False: the headline's), the particle
    time-step sweep and the FE discretisation study."""
    scene = run.scene
    rows = [bc.default_row(run.default_row, scene)]
    rows += bc.axis_defaults(scene, rows[0])
    for config in bc.configs(scene, run.quick, full):
        log.info("bench: configuration %s / %s", config.axis, config.label)
        rows.append(bc.run_config(config, scene, run.default, run.cache / "runs",
                                  ranks=run.ranks, progress=run.progress))
    rows += dt_sweep(scene, run.default, DT_FRACTIONS[run.quick])
    rows += fe_rows(scene, run.cache, run.ranks)
    bc.mark_fronts(rows)
    return {"pareto": rows}


def reference_timings_item(run: BenchRun, ranks: tuple[int, ...]) -> dict[str, Any]:
    """Wall time of the full default reference on each rank count of ``ranks``."""
    return {"reference": reference_timings(run.scene, run.default, run.cache, run.progress,
                                           ranks=ranks)}


def particle_engine(run: BenchRun) -> dict[str, Any]:
    """Kernel, gravity dynamics, term skipping, haptic latency, evaluators."""
    return particle_items(run.scene, run.default, run.quick)


def stability_limits(run: BenchRun) -> dict[str, Any]:
    """Estimated vs empirical stability limits."""
    from pipelines.bench.stability import stability_table

    return {"stability": stability_table(run.quick)}


@dataclass(frozen=True)
class ModuleItem:
    """An item in a module of its own, imported only when it runs: ``target`` =
    "module:function", function(scene, cache folder, quick) -> the bench.json keys it owns."""
    target: str

    def function(self) -> Callable[[Scene, Path, bool], dict[str, Any]]:
        module, name = self.target.split(":")
        return getattr(importlib.import_module(module), name)

    def __call__(self, run: BenchRun) -> dict[str, Any]:
        return self.function()(run.scene, run.cache, run.quick)


ItemRun = Callable[[BenchRun], dict[str, Any]]


@dataclass(frozen=True)
class Item:
    """One item of the bench: its name (logs, ``--only``, ``item_s``), what ``make
    bench-full`` runs (``full``), what ``make bench`` runs (``headline``: the same, a reduced
    version, or None: ``make bench-full`` only), whether it reads the default pipeline run
    (that one is brought up to date first by ``--only``), and whether its rows of the shared
    lists (:data:`ROW_KEYS`) carry ``"study": name`` (the default scene's own rows do not)."""
    name: str
    full: ItemRun
    headline: ItemRun | None
    needs_default: bool = False
    labels_rows: bool = True


def _same(function: ItemRun) -> tuple[ItemRun, ItemRun]:
    return function, function


#: every item, in the order a run runs them: the bench's one list of what ``make bench`` and
#: ``make bench-full`` run. ``make bench`` keeps the headline axes, speed (kernel, haptic,
#: stability) and error (run time vs error on the default scene, FE convergence, scale with
#: its growth exponents), some reduced: fewer settings per Pareto axis
#: (:data:`pipelines.bench.configs.HEADLINE_SETTINGS`), the reference on 2 ranks only, the
#: haptic meshes up to 12k connectors, the FE sag without its finest level, three scale sizes
#: without the rank timing. Left to ``make bench-full``: ``experiments`` (a reference and a
#: calibration per experiment list), ``scale reference`` (the whole FE reference on 2,936
#: vertices), ``calibration methods`` (nine pipelines on two scenes) and ``discretisation
#: floor`` (the floor's FE tests per scene).
ITEMS: tuple[Item, ...] = (
    Item("default pipeline run", *_same(default_pipeline_run), labels_rows=False),
    Item("run time vs error", partial(run_time_vs_error, full=True),
         partial(run_time_vs_error, full=False), needs_default=True, labels_rows=False),
    Item("reference timings", partial(reference_timings_item, ranks=(1, 2)),
         partial(reference_timings_item, ranks=(2,)), needs_default=True, labels_rows=False),
    Item("particle engine", *_same(particle_engine), needs_default=True, labels_rows=False),
    Item("stability limits", *_same(stability_limits), labels_rows=False),
    Item("experiments", ModuleItem("pipelines.bench.experiments:study"), None,
         needs_default=True),
    Item("haptic scale", ModuleItem("pipelines.bench.haptic:study"),
         ModuleItem("pipelines.bench.haptic:headline_study")),
    Item("fe_convergence", ModuleItem("pipelines.bench.fe_convergence:study"),
         ModuleItem("pipelines.bench.fe_convergence:headline_study")),
    Item("scale", ModuleItem("pipelines.bench.scale:study"),
         ModuleItem("pipelines.bench.scale:headline_study")),
    Item("scale reference", ModuleItem("pipelines.bench.scale:whole_reference"), None),
    Item("calibration methods", ModuleItem("pipelines.bench.calibration_methods:study"), None,
         needs_default=True),
    Item("volume term", *_same(ModuleItem("pipelines.bench.volume:study"))),
    Item("discretisation floor", ModuleItem("pipelines.bench.floor:study"), None),
)
# log messages (regular expressions) by which a cache hit announces itself: an item that logs
# one reused earlier work, so its time is not a cold time
REUSE_MESSAGES = re.compile(r"bench: reusing |up to date, skipped|already holds .* not "
                            r"recomputed|adopting the existing|resuming from checkpoint")


def items_of(full: bool) -> tuple[Item, ...]:
    """The items a whole run of ``make bench-full`` (``full``) or ``make bench`` runs, in
    order."""
    return ITEMS if full else tuple(item for item in ITEMS if item.headline is not None)


def item_run(item: Item, full: bool) -> ItemRun:
    """What ``item`` runs in ``make bench-full`` (``full``) or ``make bench``."""
    run = item.full if full else item.headline
    if run is None:
        raise ForcecalError(f"bench: {item.name!r} is an item of make bench-full only")
    return run


# ---------------------------------------------------------------------------- bench.json

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


# ---------------------------------------------------------------------------- driver

def cpu() -> dict[str, Any]:
    """The CPU's model name and widest SIMD extension (Linux ``/proc/cpuinfo``; None
    elsewhere). Two-core machines differ: the same particle kernels ran 2-4x slower on an AMD
    EPYC with AVX2 than on one with AVX-512."""
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
    pipeline run when one of them ``needs_default`` (:data:`ITEMS`). All of them are
    recorded in ``reruns``: the default run rewrites its keys (the calibration block,
    goals) too."""
    needs_default = {item.name for item in ITEMS if item.needs_default}
    keep = {"default pipeline run"} if set(only) & needs_default else set()
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


def merge_keys(bench: dict[str, Any], keys: dict[str, Any], item: Item) -> None:
    """Put the bench.json ``keys`` an item returned into ``bench``: each replaces the earlier
    value, but a shared list of rows (:data:`ROW_KEYS`) keeps the rows of other items: the
    item's rows replace only its own (labelled ``"study": name`` unless the item is one of the
    default scene's, whose rows are not labelled)."""
    label = item.name if item.labels_rows else None
    for key, value in keys.items():
        if key in ROW_KEYS:
            value = [r for r in bench.get(key, []) if r.get("study") != label] + [
                {**r, "study": label} if label else r for r in value]
        bench[key] = value


def run_bench(out: Path, *, full: bool = False, quick: bool = False,
              scene_path: Path | None = None, ranks: int = 2, progress: bool = True,
              only: tuple[str, ...] = (), cold: bool = False) -> dict[str, Any]:
    """The items of ``make bench`` or, ``full``, of ``make bench-full`` (:data:`ITEMS`, in
    order); writes bench.json, pareto.png, BENCH.md in ``out``.

    ``only`` names the items to run (their keys replace those of the ``bench.json``
    already in ``out``, the rest are kept as they are; the default pipeline run is
    brought up to date first when an item needs it). ``cold``: measure the cold wall time
    (module docstring); needs an empty ``out/cache`` and no ``only``.
    """
    from pipelines.bench.report import write_markdown, write_pareto_plot

    scene = load_scene(scene_path or ROOT / "scenes" / ("tiny.toml" if quick else "liver.toml"))
    names = [item.name for item in ITEMS]
    if only:  # refused before anything runs or is written
        unknown = sorted(set(only) - set(names))
        if unknown:
            raise ForcecalError(f"bench --only: unknown item(s) {unknown}; known: {names}")
        full_only = sorted(set(only) - {item.name for item in items_of(full)})
        if full_only:
            raise ForcecalError(f"bench --only: {full_only} run in make bench-full only: pass "
                                "--full (and its folder, runs/bench by default)")
    cache = out / "cache"
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
    if only:
        previous = whole_run(out, scene.name, quick, full)
        run_names = selected_items(names, only)
        bench = partial_bench(previous, bench["machine"], run_names, scene.name, quick, full)
    else:  # the last whole run's cold times, if it ran the same selection
        previous = json.loads((out / "bench.json").read_text()) if (
            out / "bench.json").is_file() else {}
        if previous and (selection(previous), previous.get("scene"), bool(previous.get(
                "quick"))) != (bench["selection"], scene.name, quick):
            previous = {}
        run_names = tuple(item.name for item in items_of(full))
    items = [item for item in ITEMS if item.name in run_names]
    run = BenchRun(scene, cache, quick, ranks, progress)
    bench["item_s"] = dict(bench.get("item_s", {}))
    reused: set[str] = set()
    start = time.perf_counter()
    for k, item in enumerate(items, 1):
        log.info("bench [%d/%d] %s ...", k, len(items), item.name)
        counter = ReuseCounter()
        logging.getLogger().addHandler(counter)
        t0 = time.perf_counter()
        try:
            merge_keys(bench, item_run(item, full)(run), item)
        finally:
            logging.getLogger().removeHandler(counter)
        bench["item_s"][item.name] = time.perf_counter() - t0
        if counter.hits:
            reused.add(item.name)
        log.info("bench [%d/%d] %s done in %.1f s%s", k, len(items), item.name,
                 bench["item_s"][item.name], " (reused earlier work)" if counter.hits else "")
    if not only:  # a partial run keeps the whole run's wall time
        bench["wall_s"] = time.perf_counter() - start
    if cold:  # everything was computed in this run (reuse between its items included)
        bench["item_s_cold"] = dict(bench["item_s"])
    else:  # a partial run keeps the other items' cold times
        bench["item_s_cold"] = {**(previous.get("item_s_cold", {}) if only else {}),
                                **cold_times({i.name: bench["item_s"][i.name] for i in items},
                                             reused, previous)}
    cold_s = list(bench["item_s_cold"].values())
    bench["wall_s_cold"] = (None if None in cold_s or set(bench["item_s_cold"]) != set(
        bench["item_s"]) else float(sum(cold_s)))
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
    run_bench(out, full=args.full, quick=args.quick,
              scene_path=Path(args.scene) if args.scene else None, ranks=args.ranks, progress=not args.no_progress,
              only=tuple(name.strip() for name in args.only.split(",") if name.strip()),
              cold=args.cold)
    print(f"bench: outputs in {out}/ (bench.json, pareto.png, BENCH.md)")
    return 0
