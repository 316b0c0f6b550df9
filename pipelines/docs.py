"""Generated documentation: every results, benchmark and schema table of the README and ``docs/``.

``python -m pipelines docs`` rewrites the text between marker comments::

    <!-- generated: NAME -->
    ...
    <!-- end generated -->

in ``README.md`` and every ``docs/*.md`` from the committed results, so no number in the
documentation is typed in by hand (``--check`` only lists what is stale). Block names
(:func:`render`):

* ``results``: one table per shipped scene (every ``runs/<scene>/report.json``): the
  calibrated model's and the closed-form baseline's held-out indentation and relaxation
  errors, static sag, release period, first peak and RMS, and the verdict
  (``report.json``'s ``verdict`` block; a report written before the verdict existed says so);
* ``details SCENE``: the scene's full error and timing tables
  (:func:`pipelines.report.results_markdown`), its release against the FE's and, when the
  report has them, the force vector's errors;
* ``verdicts``: every shipped scene's verdict table (:func:`pipelines.verdict.verdict_markdown`;
  a report without a verdict is judged from its measurements against the default goals,
  as ``python -m pipelines verdict-table`` does, and labelled so);
* ``bench goals``, ``bench scale``, ``bench fe convergence``, ``bench duration``,
  ``bench floor``: the goals, scale, FE convergence and discretisation floor tables of
  ``runs/bench/bench.json`` and its cold run time;
* ``scene keys``: the table of every scene key (:func:`forcecal.scene.keys_table`);
* ``schema MODULE``: a file's schema table from the docstring of the module that writes it
  (:data:`SCHEMA_MODULES`: ``params.h5``, ``gravity.h5``).

``docs/corpus.md`` is a whole generated page: when ``runs/corpus/corpus.json`` exists it is
rewritten with :func:`pipelines.corpus.corpus_markdown` (``python -m pipelines corpus
--table`` writes the same); ``docs/corpus_recipe.md`` likewise from
``runs/corpus_recipe/corpus.json`` (``corpus --recipe --table``).
"""
from __future__ import annotations

import argparse
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from forcecal.errors import DataFileError
from forcecal.h5io import atomic_path

BLOCK = re.compile(r"(<!-- generated: (?P<name>[^>]+?) -->\n)(?P<body>.*?)"
                   r"(<!-- end generated -->)", re.S)
NO_VERDICT = "no verdict (report predates it)"
#: ``gravity.dynamic_metrics`` value -> its signed relative error against the FE's
ERROR_KEYS = {"period_s": "period_error", "first_peak_m": "first_peak_error",
              "decay_rate_1_per_s": "decay_rate_error"}


@dataclass(frozen=True)
class Sources:
    """Where the generated numbers come from (the project root's ``runs/`` by default)."""
    root: Path

    @property
    def runs(self) -> Path:
        return self.root / "runs"

    def scenes(self) -> list[str]:
        """The shipped scenes: every ``runs/<name>/report.json`` of a ``scenes/<name>.toml``
        (a scratch run under ``runs/`` in another folder is no shipped scene), the default
        liver first."""
        names = sorted(p.parent.name for p in self.runs.glob("*/report.json")
                       if (self.root / "scenes" / f"{p.parent.name}.toml").is_file())
        return sorted(names, key=lambda n: n != "liver")

    def report(self, scene: str) -> dict[str, Any]:
        from pipelines.report import read_report
        return read_report(self.runs / scene / "report.json")

    def bench(self) -> dict[str, Any]:
        from pipelines.bench.driver import read_bench
        return read_bench(self.runs / "bench" / "bench.json")


def _percent(value: float | None, signed: bool = False) -> str:
    if value is None:
        return "n/a"
    return f"{100 * value:+.1f} %" if signed else f"{100 * value:.2f} %"


def scene_line(report: dict[str, Any], root: Path) -> str:
    """What the scene is: indenter, model, method, mesh and test points (from the report and,
    when it is there, ``scenes/<name>.toml``)."""
    name = report["scene"]
    mesh, points = report["mesh"], report["test_points"]
    what = [f"{mesh['nodes']} vertices, {mesh['connectors']} connectors",
            f"{len(points['calibration'])} calibration + {len(points['held_out'])} held-out "
            "points"]
    path = root / "scenes" / f"{name}.toml"
    if path.is_file():
        from forcecal.scene import load_scene
        s = load_scene(path)
        ind, p, c = s.indentation, s.particle, s.calibration
        model = {False: "springs", True: "springs + volume term",
                 "viscoelastic": "springs + relaxing volume term"}[p.volume]
        fit = [f"{c.method} method"]
        if c.method == "gradient" and c.force_components == "vector":
            fit.append("force vector")
        if c.global_shape != "uniform":
            fit.append(f"{c.global_shape.replace('_', ' ').title()} global shape")
        indenter = ("vertex indenter" if ind.indenter == "vertex"
                    else f"{1000 * ind.radius:.1f} mm punch")
        what = [indenter, model, ", ".join(fit)] + what
        return f"**`{name}`** (`scenes/{name}.toml`): " + "; ".join(what)
    return f"**`{name}`**: " + "; ".join(what)


def summary_table(report: dict[str, Any]) -> str:
    """One scene's results at a glance: calibrated vs baseline on the checks the verdict
    judges, and the verdict (or that the report predates it)."""
    from pipelines.verdict import CHECKS, verdict_line
    e, b = report["errors"], report["baseline_errors"]
    metrics = (report.get("gravity") or {}).get("dynamic_metrics") or {}

    def row(label: str, errors: dict[str, Any], model: str) -> list[str]:
        m = metrics.get(model) or {}
        return [label, _percent(errors["indentation_held_out"]),
                _percent(errors["relaxation_held_out"]), _percent(errors["gravity_static"]),
                _percent(m.get("period_error"), signed=True),
                _percent(m.get("first_peak_error"), signed=True),
                _percent(errors["gravity_dynamic"])]

    header = ["model", "held-out indentation", "held-out relaxation", "static sag",
              "release period", "release first peak", "release RMS"]
    rows = [row("calibrated", e, "calibrated"), row("closed-form baseline", b, "baseline")]
    verdict = report.get("verdict")
    if verdict is None:
        last = f"Verdict: {NO_VERDICT}."
    else:
        checks = [verdict["checks"].get(n) for n in ("held_out_indentation",
                                                      "held_out_relaxation", "static_sag",
                                                      "release_period", "release_first_peak",
                                                      "release_rms")]
        rows.append(["goal"] + [
            "" if c is None else f"{'<=' if CHECKS[n].direction == 'at most' else '>='} "
            f"{_percent(c['goal'])}" for n, c in zip(list(CHECKS)[:6], checks)])
        rows.append(["status"] + ["" if c is None else f"**{c['status'].replace('_', ' ')}**"
                                  for c in checks])
        last = f"Verdict: {verdict_line(verdict).split(': ', 1)[1]}."
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines + ["", last])


def release_table(report: dict[str, Any]) -> str:
    """The tracked vertex's release: FE, calibrated and baseline period, first peak, decay
    rate and the two modes that carry most of its motion; the largest static sag."""
    g = report.get("gravity") or {}
    metrics = g.get("dynamic_metrics")
    if not metrics:
        return "(no gravity release in this report)"

    def cell(model: str, key: str, unit: float, fmt: str, name: str) -> str:
        m = metrics.get(model) or {}
        if m.get(key) is None:
            return "n/a"
        text = f"{unit * m[key]:{fmt}} {name}"
        error = m.get(ERROR_KEYS[key])
        return text if error is None else f"{text} ({_percent(error, True)})"

    def modes(model: str) -> str:
        m = metrics.get(model) or {}
        found = m.get("modes") or []
        errors = m.get("mode_frequency_errors") or [None] * len(found)
        return ", ".join(f"{x['frequency_hz']:.2f} Hz" + (
            f" ({_percent(err, True)})" if err is not None else
            f" ({1000 * x['amplitude_m']:.1f} mm)") for x, err in zip(found, errors)) or "n/a"

    sag = [g.get(f"{k}_max_static_sag_m") for k in ("fe", "calibrated", "baseline")]
    rows = [["dominant period (first {:g} s)".format(metrics.get("window_s", 1.5))]
            + [cell(k, "period_s", 1.0, ".3f", "s") for k in ("fe", "calibrated", "baseline")],
            ["first peak"] + [cell(k, "first_peak_m", 1000.0, ".1f", "mm")
                              for k in ("fe", "calibrated", "baseline")],
            ["decay rate"] + [cell(k, "decay_rate_1_per_s", 1.0, ".3f", "1/s")
                              for k in ("fe", "calibrated", "baseline")],
            ["two leading modes"] + [modes(k) for k in ("fe", "calibrated", "baseline")],
            ["largest static sag"] + ["n/a" if s is None else f"{1000 * s:.1f} mm" for s in sag]]
    lines = [f"| tracked vertex {g.get('tracked_node')} | FE | calibrated | baseline |",
             "|---|---|---|---|"]
    return "\n".join(lines + ["| " + " | ".join(r) + " |" for r in rows])


def force_vector_table(report: dict[str, Any]) -> str | None:
    """The whole indenter force's errors (``force_vector_errors``: the vector and its
    tangential part, on the normal curve's scale), calibrated and baseline; None for a
    report without them."""
    vector = report.get("force_vector_errors")
    if not vector:
        return None

    def pair(errors: dict[str, Any], points: str) -> str:
        return " / ".join(_percent(errors.get(f"{e}_{points}")).removesuffix(" %")
                          for e in ("indentation", "relaxation")) + " %"

    rows = ["| force vector error (indentation / relaxation) | calibration points | "
            "held-out points |", "|---|---|---|"]
    for key, label in (("calibrated", "calibrated, whole vector"),
                       ("calibrated_tangential", "calibrated, tangential part"),
                       ("baseline", "baseline, whole vector"),
                       ("baseline_tangential", "baseline, tangential part")):
        if key in vector:
            rows.append(f"| {label} | {pair(vector[key], 'calibrated')} | "
                        f"{pair(vector[key], 'held_out')} |")
    return "\n".join(rows)


def report_verdict(report: dict[str, Any]) -> tuple[dict[str, Any], bool]:
    """The report's verdict block, or (for a report written before it existed) its
    measurements judged now against the default ``[verdict]`` goals; and whether it was
    judged now."""
    if "verdict" in report:
        return report["verdict"], False
    from forcecal.scene import VerdictSection
    from pipelines.verdict import judge, measurements
    return judge(measurements(report), VerdictSection()), True


def _results(src: Sources) -> str:
    parts = []
    for name in src.scenes():
        report = src.report(name)
        parts += [scene_line(report, src.root), "", summary_table(report), ""]
    return "\n".join(parts).rstrip("\n")


def _details(src: Sources, scene: str) -> str:
    from pipelines.report import results_markdown
    report = src.report(scene)
    parts = [results_markdown(report), "", release_table(report)]
    vector = force_vector_table(report)
    return "\n".join(parts + ([] if vector is None else ["", vector]))


def _verdicts(src: Sources) -> str:
    from pipelines.verdict import verdict_markdown
    parts = []
    for name in src.scenes():
        verdict, judged_now = report_verdict(src.report(name))
        note = (" (the report predates the verdict: its measurements judged now against the "
                "default goals)" if judged_now else "")
        parts += [f"`{name}`{note}:", "", verdict_markdown(verdict), ""]
    return "\n".join(parts).rstrip("\n")


def _bench_goals(src: Sources) -> str:
    from pipelines.bench.report import goals_markdown
    return goals_markdown(src.bench())


def bench_duration(bench: dict[str, Any]) -> str:
    """How long the committed benchmark run takes with nothing cached, item by item."""
    m = bench["machine"]
    cold = bench.get("item_s_cold") or {}
    if bench.get("wall_s_cold") is None:
        return "(this bench.json predates the cold timings)"
    items = ", ".join(f"{name} {seconds / 60:.1f}"
                      for name, seconds in sorted(cold.items(), key=lambda kv: -kv[1]))
    return (f"With nothing cached the committed run takes {bench['wall_s_cold'] / 60:.1f} min "
            f"on {m['cpu_count']} cores ({m.get('cpu_model', '?')}, {m.get('simd', '?')}); per "
            f"item, in minutes: {items}.")


def _bench_duration(src: Sources) -> str:
    return bench_duration(src.bench())


def _bench_scale(src: Sources) -> str:
    from pipelines.bench.scale import scale_table
    return scale_table(src.bench())


def fe_convergence_table(study: dict[str, Any]) -> str:
    """The punch force and static sag of ``bench["fe_convergence"]`` per rim refinement
    level, with the changes the study summarises."""
    levels = study["levels"]
    rows = ["| rim level | dofs (one per punch) | punch force at "
            f"{1000 * study['depth_m']:g} mm [N] | change to next level | clamp rim: dofs, "
            "max static sag |", "|---|---|---|---|---|"]
    for i, lv in enumerate(levels):
        nxt = levels[i + 1] if i + 1 < len(levels) else None
        change = "" if nxt is None else " / ".join(
            f"{100 * (b / a - 1):+.2f} %" for a, b in zip(lv["punch_force"], nxt["punch_force"]))
        sag = ("not computed" if lv.get("max_sag") is None
               else f"{lv['sag_dofs']}, {1000 * lv['max_sag']:.2f} mm")
        level = (f"**{lv['level']} (scene)**" if lv["level"] == study["default_level"]
                 else str(lv["level"]))
        rows.append(f"| {level} | {' / '.join(str(d) for d in lv['dofs'])} | "
                    f"{' / '.join(f'{f:.3f}' for f in lv['punch_force'])} | {change} | {sag} |")
    rows += ["", f"`punch_force_change` (the scene's level {study['default_level']} against the "
             f"finest, {study['finest_level']}): {100 * study['punch_force_change']:.2f} %; "
             f"`sag_change` (the gravity runs' mesh, level {study['default_sag_level']}, against "
             f"the finest sag level, {study['finest_sag_level']}): "
             f"{100 * study['sag_change']:.1f} %. Points {study['points']}, punch radius "
             f"{1000 * study['radius_m']:g} mm, scene `{study['scene']}`."]
    return "\n".join(rows)


def _bench_fe_convergence(src: Sources) -> str:
    return fe_convergence_table(src.bench()["fe_convergence"])


def _bench_floor(src: Sources) -> str:
    from pipelines.bench.floor import floor_table
    return "\n".join(floor_table(src.bench()["discretisation_floor"]))


#: modules whose docstring holds a file's schema table (``schema MODULE`` blocks)
SCHEMA_MODULES = ("calibration.results", "pipelines.gravity")


def schema_table(module: str) -> str:
    """The schema table of a file format, as the module that writes it documents it (the
    lines of its docstring that are Markdown table rows)."""
    if module not in SCHEMA_MODULES:
        raise DataFileError(f"no schema table in '{module}' (known: {', '.join(SCHEMA_MODULES)})")
    import importlib
    doc = importlib.import_module(module).__doc__ or ""
    return "\n".join(line for line in doc.splitlines() if line.startswith("|"))


def _scene_keys(src: Sources) -> str:
    from forcecal.scene import keys_table
    return keys_table()


RENDERERS: dict[str, Callable[[Sources], str]] = {
    "results": _results, "verdicts": _verdicts, "bench goals": _bench_goals,
    "bench scale": _bench_scale, "bench fe convergence": _bench_fe_convergence,
    "bench duration": _bench_duration, "bench floor": _bench_floor,
    "scene keys": _scene_keys}


def render(name: str, src: Sources) -> str:
    """The text of the generated block ``name`` (module docstring)."""
    if name in RENDERERS:
        return RENDERERS[name](src)
    kind, _, arg = name.partition(" ")
    if kind == "details" and arg:
        return _details(src, arg)
    if kind == "schema" and arg:
        return schema_table(arg)
    raise DataFileError(f"unknown generated block '{name}' (known: "
                        f"{', '.join(sorted(RENDERERS))}, details SCENE, schema MODULE)")


def regenerate(text: str, src: Sources) -> str:
    """``text`` with every generated block's body rendered anew."""
    return BLOCK.sub(lambda m: f"{m.group(1)}{render(m.group('name').strip(), src)}\n"
                     f"{m.group(4)}", text)


def pages(root: Path) -> list[Path]:
    """The Markdown pages that hold generated blocks: ``README.md`` and ``docs/*.md``."""
    readme = root / "README.md"
    return [readme] * readme.is_file() + sorted((root / "docs").glob("*.md"))


def generated(root: Path) -> dict[Path, str]:
    """Every page's text as ``python -m pipelines docs`` writes it (pages without blocks
    unchanged); ``docs/corpus.md`` from ``runs/corpus/corpus.json`` and
    ``docs/corpus_recipe.md`` from ``runs/corpus_recipe/corpus.json`` when they exist."""
    src = Sources(root)
    out = {path: regenerate(path.read_text(), src) for path in pages(root)}
    from pipelines.corpus import DOCS, OUT, RECIPE_DOCS, RECIPE_OUT, corpus_markdown, read_corpus
    for runs, page in ((OUT, DOCS), (RECIPE_OUT, RECIPE_DOCS)):
        data = root / runs / "corpus.json"
        if data.is_file():
            out[root / page] = corpus_markdown(read_corpus(data))
    return out


def stale_of(fresh: dict[Path, str]) -> list[Path]:
    """The pages of ``fresh`` (:func:`generated`) whose committed text differs."""
    return [path for path, text in fresh.items()
            if not path.is_file() or path.read_text() != text]


def stale(root: Path) -> list[Path]:
    """The pages whose committed text differs from what ``python -m pipelines docs`` writes."""
    return stale_of(generated(root))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``docs`` subcommand's options (used by :mod:`pipelines.cli`)."""
    parser.add_argument("--root", type=Path, default=Path("."),
                        help="project root holding README.md, docs/ and runs/ (default: .)")
    parser.add_argument("--check", action="store_true",
                        help="write nothing; list the stale pages and exit 1 if there are any")


def main(args: argparse.Namespace) -> int:
    """``python -m pipelines docs``: rewrite the generated blocks (or, ``--check``, list the
    stale pages)."""
    fresh = generated(args.root)
    changed = {path: fresh[path] for path in stale_of(fresh)}
    for path, text in changed.items():
        if args.check:
            print(f"stale: {path}")
            continue
        with atomic_path(path) as tmp:
            tmp.write_text(text)
        print(f"rewrote {path}")
    if not changed:
        print("every generated block is current")
    return 1 if args.check and changed else 0
