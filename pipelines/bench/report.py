"""``BENCH.md`` and ``pareto.png`` from ``bench.json`` (see :mod:`pipelines.bench`)."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from forcecal.h5io import atomic_path
from pipelines.bench import haptic as bench_haptic
from pipelines.bench import floor as bench_floor
from pipelines.bench import calibration_methods
from pipelines.bench.items import GOALS
from pipelines.bench.tables import cell, table

log = logging.getLogger(__name__)

AXES = ("mesh", "calibration points", "Nelder-Mead budget", "local tuning", "particle dt",
        "FE discretisation")
ERROR_LABEL = {
    "particle dt": "tracked-vertex history: change vs smallest dt",
    "FE discretisation": "max static sag: change vs refined P2",
}
DEFAULT_ERROR_LABEL = "held-out curve error (indentation, relaxation)"
# why the default setting stays where it is when another one dominates it
WHY_DEFAULT = {
    "particle dt": "the limit is a rigorous bound over the release's strain range, which the "
                   "run verifies; particle.dt_safety keeps a margin below it, and the error "
                   "against the FE does not depend on the step here (the model error dominates "
                   "the time-discretisation error)",
    "mesh": "the error is measured against each mesh's own FE reference (vertex indentation has "
            "no mesh-converged force), so a coarser mesh is not a less accurate model of the "
            "same FE; the default keeps the paper's resolution (~270 nodes)",
    "calibration points": "fewer calibration points tune fewer connectors: the curves of "
                          "the surface vertices between them are not fitted, while the "
                          "held-out set (the same points for every setting) samples only a "
                          "few of them; differences of about 0.01 are within the spread "
                          "between points and the calibration times were measured under "
                          "different loads",
    "Nelder-Mead budget": "what the budget buys is the fit at the calibration points (the "
                          "*_calibrated columns), not the held-out error, which the local "
                          "fits barely move; the default lets every local fit of the liver "
                          "meet its tolerance (a smaller budget stops them part-way: "
                          "a warning per stage)",
    "local tuning": "local tuning is what fits the calibration points themselves (the "
                    "*_calibrated columns); the held-out points measure how that carries over "
                    "to points it was not fitted to, and it does not",
    "FE discretisation": "the particle model fitted to the Taylor-Hood reference's (softer) "
                         "indentation curves cannot carry the organ's weight: its static sag "
                         "has no equilibrium beyond about 0.85 g (docs/limitations.md), so "
                         "the default is the P2 reference a particle model can be fitted to end "
                         "to end, with its 15 % stiffness in sag stated; the refined mesh is "
                         "too slow for routine use",
}


def selection(bench: dict[str, Any]) -> str:
    """"headline" (``make bench``) or "full" (``make bench-full``; runs written before the
    headline existed ran every item)."""
    return bench.get("selection", "full")


def _rows(bench: dict, axis: str) -> list[dict]:
    return [r for r in bench["pareto"] if r["axis"] == axis]


def _scale(axis, set_scale, values: np.ndarray) -> None:
    """Log scale for positive data spanning more than a decade, else linear; plain ticks."""
    from matplotlib.ticker import FuncFormatter, NullFormatter, ScalarFormatter

    if values.min() > 0 and values.max() > 10 * values.min():
        set_scale("log")
        axis.set_minor_formatter(NullFormatter())
        # ScalarFormatter mislabels log axes (decades shown as 0.00, 0.01, ...)
        axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        return
    formatter = ScalarFormatter()
    formatter.set_scientific(True)
    formatter.set_powerlimits((-2, 3))
    axis.set_major_formatter(formatter)


def _merged_labels(labels: list[str], screen: np.ndarray) -> dict[int, str]:
    """One annotation per group of points that nearly coincide on screen (``screen``: (n, 2)
    display coordinates [px]), e.g. ``P2 q=4 / P2 q=6``, so labels do not print over each other."""
    out: dict[int, str] = {}
    taken = np.zeros(len(labels), dtype=bool)
    for k in range(len(labels)):
        if taken[k]:
            continue
        dx, dy = np.abs(screen - screen[k]).T
        near = (dx < 60.0) & (dy < 12.0) & ~taken  # about a label's width and height
        taken |= near
        group = np.nonzero(near)[0]
        # written right of the group's rightmost point, clear of the others' markers
        out[int(group[np.argmax(screen[group, 0])])] = " / ".join(labels[i] for i in group)
    return out


def write_pareto_plot(path: Path, bench: dict[str, Any]) -> None:
    """One panel per axis: wall time of the stage it affects vs its error, front and default."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    axes = [a for a in AXES if any("failed" not in r for r in _rows(bench, a))]
    fig, panels = plt.subplots(2, 3, figsize=(15, 9.5))
    for ax, axis in zip(panels.ravel(), axes):
        rows = [r for r in _rows(bench, axis) if "failed" not in r]
        t = np.array([r["wall_s"] for r in rows])
        e = np.array([r["errors"]["overall"] for r in rows])
        positive = e[e > 0] if np.any(e > 0) else np.array([1e-6])
        wide = positive.max() > 10 * positive.min()
        # on a log axis an exact reference (error 0) sits on a floor below the others
        shown = np.where(e > 0, e, 0.5 * positive.min()) if wide else e
        front = np.array([r.get("on_front", False) for r in rows])
        order = np.argsort(t[front])
        ax.plot(t[front][order], shown[front][order], "-", color="tab:green", lw=2, alpha=0.5,
                label="Pareto front")
        ax.scatter(t, shown, c=np.where(front, "tab:green", "tab:gray"), s=50, zorder=3)
        for r, x, y in zip(rows, t, shown):
            if r["default"]:
                ax.scatter([x], [y], marker="*", s=260, facecolor="none", edgecolor="tab:red",
                           lw=1.8, zorder=4, label="default scene")
        _scale(ax.xaxis, ax.set_xscale, t)
        _scale(ax.yaxis, ax.set_yscale, shown)
        ax.set_title(axis)
        ax.set_xlabel(f"wall time [s]: {rows[0]['stage']}", fontsize=8)
        ax.set_ylabel(ERROR_LABEL.get(axis, DEFAULT_ERROR_LABEL))
        ax.grid(True, which="both", alpha=0.3)
        ax.margins(x=0.3, y=0.2)
        if not wide and np.ptp(shown) < 0.2 * shown.max():
            # differences far below the error itself: show them at that scale, not magnified
            mid = 0.5 * (shown.max() + shown.min())
            ax.set_ylim(0.85 * mid, 1.15 * mid)
        # labelled last, in screen space once the scales and limits are final
        labels = [r["label"] + (" (= 0)" if z <= 0 else "") for r, z in zip(rows, e)]
        screen = ax.transData.transform(np.column_stack([t, shown]))
        for k, text in _merged_labels(labels, screen).items():
            ax.annotate(text, (t[k], shown[k]), textcoords="offset points", xytext=(6, 4),
                        fontsize=8)
    handles, labels = panels.ravel()[0].get_legend_handles_labels()
    for ax in panels.ravel()[:len(axes)]:
        more = ax.get_legend_handles_labels()
        handles, labels = handles + more[0], labels + more[1]
    unique = dict(zip(labels, handles))
    fig.legend(unique.values(), unique.keys(), loc="lower center", ncol=len(unique), fontsize=10,
               title="green: on the panel's Pareto front")
    failed = [a for a in AXES if _rows(bench, a) and a not in axes]
    for k, ax in enumerate(panels.ravel()[len(axes):]):
        ax.axis("off")
        if k < len(failed):
            ax.text(0.5, 0.6, f"{failed[k]}:\nfailed, see BENCH.md", ha="center",
                    va="center", fontsize=12, color="tab:red", transform=ax.transAxes)
    fig.suptitle(f"forcecal run time vs error ({bench['scene']}; "
                 f"{bench['machine']['date'][:10]}, "
                 f"load {bench['machine']['load_average_start'][0]:.1f})")
    fig.tight_layout(rect=(0, 0.07, 1, 1))  # room for the legend below the panels
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


def _goal(measured: float | None, goal: float, below: bool = True) -> str:
    if measured is None:
        return "not measured"
    met = measured <= goal if below else measured >= goal
    return "**met**" if met else "**missed**"


def _goals_section(b: dict) -> list[str]:
    k, g, c, r = b["kernel"], b["gravity_dynamic"], b["calibration"], b["reference"]
    h = b["haptic"]
    ratio, haptic_us = GOALS["numpy_ratio"], GOALS["haptic_us"]
    per_3s = GOALS["gravity_3s_s"]  # [s] per 3 s simulated
    gravity_s, calibration_s = per_3s * g["duration_s"] / 3, GOALS["calibration_s"]
    reference_s = GOALS["reference_2ranks_s"]
    rows = [
        ["compiled step vs numpy step (liver)", f">= {ratio:g}x", f"{k['numpy_ratio']:.1f}x",
         _goal(k["numpy_ratio"], ratio, below=False)],
        ["compiled step vs numpy step (>= 10k connectors)", f">= {ratio:g}x",
         f"{k['large']['speedup']:.1f}x", _goal(k["large"]["speedup"], ratio, below=False)],
        [f"{g['duration_s']:g} s gravity dynamics, calibrated model",
         f"<= {gravity_s:.3g} s ({per_3s:g} s per 3 s)", f"{g['particle_s']:.3g} s",
         _goal(g["particle_s"], gravity_s)],
        ["haptic step (1 ms simulated), liver, p99", f"<= {haptic_us:g} us",
         f"{h['liver']['p99_us']:.0f} us (median {h['liver']['median_us']:.0f})",
         _goal(h["liver"]["p99_us"], haptic_us)],
        [f"haptic step, {h['large']['connectors']} connectors, p99", f"<= {haptic_us:g} us",
         f"{h['large']['p99_us']:.0f} us (median {h['large']['median_us']:.0f})",
         _goal(h["large"]["p99_us"], haptic_us)],
        *([[f"haptic step, {h['large_2threads']['connectors']} connectors, 2 threads "
            "(renumbered), p99", f"<= {haptic_us:g} us",
            f"{h['large_2threads']['p99_us']:.0f} us (median "
            f"{h['large_2threads']['median_us']:.0f})",
            _goal(h["large_2threads"]["p99_us"], haptic_us)]] if "large_2threads" in h else []),
        *bench_haptic.goal_rows(b),
        [f"calibration, {b['scene']} scene", f"<= {calibration_s:g} s", f"{c['wall_s']:.0f} s",
         _goal(c["wall_s"], calibration_s)],
        ["full FE reference, 2 ranks", f"<= {reference_s / 60:g} min",
         f"{r['wall_s_2ranks'] / 60:.1f} min", _goal(r["wall_s_2ranks"], reference_s)],
        *_punch_calibration_rows(b),
        *_scale_reference_rows(b),
    ]
    return table(["goal (issues)", "target", "measured", ""], rows)


def _punch_calibration_rows(b: dict) -> list[list[str]]:
    """The goal row of the punch + whole-body method's calibration time on the punch scene
    (its row of the ``calibration methods`` item: the scene's own volume term and
    ``calibration.body_data``); none before that item has run."""
    rows = [r for r in b.get("calibration_methods", [])
            if r["method"] == calibration_methods.BODY_METHOD
            and r["scene"] == calibration_methods.PUNCH_SCENE.stem]
    if not rows:
        return []
    r, goal = rows[0], GOALS["punch_body_calibration_s"]
    name = f"calibration, {r['scene']} scene, {r['model']}, {r['method']}, 2 cores"
    if "failed" in r:
        return [[name, f"<= {goal:.0f} s", "failed", "**missed**"]]
    return [[name, f"<= {goal:.0f} s", f"{r['calibration_s']:.0f} s",
             _goal(r["calibration_s"], goal)]]


def _scale_reference_rows(b: dict) -> list[list[str]]:
    """The goal row of the whole FE reference on the scale study's largest mesh (``make
    bench-full`` only: none before that item has run)."""
    if "scale_reference" not in b:
        return []
    s = b["scale_reference"]
    return [[f"full FE reference, {s['vertices']} vertices, {s['ranks']} ranks (whole run)",
             "<= 30 min", f"{s['wall_s'] / 60:.1f} min (load {s['load_average'][0][0]:.1f}"
             f" at start, {s['load_average'][1][0]:.1f} at end)", _goal(s["wall_s"], 1800.0)]]


def _duration(b: dict) -> str:
    """How long this bench run took, item by item (runs written before it was recorded: '')."""
    if "wall_s" not in b:
        return ""
    items = ", ".join(f"{name} {seconds / 60:.1f}" for name, seconds in b["item_s"].items())
    # ``--only`` runs update their items' times but not ``wall_s`` (the last full run's)
    text = (f"The last whole run took {b['wall_s'] / 60:.1f} min; each item's time in the run "
            f"that last ran it: {items} min.")
    if b.get("wall_s_cold") is not None:  # runs written before it was recorded have none
        text += (f" With nothing cached (each item's time when it last reused nothing) it "
                 f"takes {b['wall_s_cold'] / 60:.1f} min.")
    for r in b.get("reruns", []):  # ``--only`` runs since: their items' numbers are theirs
        text += (f" Rerun alone since ({', '.join(r['items'])}): on {r['date']}, commit "
                 f"`{r['git_commit']}`, load average at start {r['load_average_start'][0]:.2f}.")
    return text


def goals_markdown(b: dict[str, Any]) -> str:
    """The goals table of ``BENCH.md`` (docs/benchmarks.md shows it: ``python -m pipelines
    bench-table runs/bench/bench.json``)."""
    return "\n".join(_goals_section(b))


def _pareto_section(b: dict) -> list[str]:
    lines = []
    for axis in AXES:
        rows = _rows(b, axis)
        done = [r for r in rows if "failed" not in r]
        if not done:
            lines += ["", f"### {axis}", ""] + [f"Failed: {r['label']}: `{r['failed']}`"
                                                 for r in rows]
            continue
        keys = [k for k in done[0]["errors"] if k != "overall"]
        lines += ["", f"### {axis}", "", f"Stage timed: {done[0]['stage']}. Pareto error: "
                  f"{ERROR_LABEL.get(axis, DEFAULT_ERROR_LABEL)}.", ""]
        lines += table(["setting", "wall [s]"] + keys + ["Pareto error", "front", "default"],
                       [[r["label"], r["wall_s"]] + [r["errors"][k] for k in keys]
                        + [r["errors"]["overall"], r["on_front"], r["default"]]
                        for r in done])
        lines += [f"\nFailed: {r['label']}: `{r['failed']}`" for r in rows if "failed" in r]
        lines += [f"\nGravity stage failed for {r['label']}: `{r['gravity_failed']}`"
                  for r in done if "gravity_failed" in r]
        default = [r for r in rows if r["default"]]
        if default and not default[0].get("on_front"):
            better = [r["label"] for r in rows if r.get("on_front") and
                      r["wall_s"] <= default[0]["wall_s"] and
                      r["errors"]["overall"] <= default[0]["errors"]["overall"]]
            lines += ["", f"The default ({default[0]['label']}) is **not** on the front "
                      f"(dominated by {', '.join(better) or 'another setting'}); it stays the "
                      f"default because {WHY_DEFAULT[axis]}."]
        elif default:
            lines += ["", f"The default ({default[0]['label']}) is on the front."]
    return lines


def _mesh_protocol(b: dict) -> str:
    """How the mesh panel's reduced experiments were run (from their configurations)."""
    rows = _rows(b, "mesh")
    if not rows:
        return ""
    n_cal, n_held = rows[0]["config"]["points"]
    return (f"The mesh panel uses a **reduced experiment set** at every level ({n_cal} "
            f"calibration points spread over the surface, {n_held} held-out points, the scene's "
            "indentation and relaxation schedules, the static sag and "
            f"{rows[0]['config']['gravity_duration_s']:g} s of gravity dynamics), each level "
            "with its own FE reference.")


def write_markdown(path: Path, b: dict[str, Any]) -> None:
    """``BENCH.md``: every number of ``bench.json`` with how it was measured."""
    m, k, g = b["machine"], b["kernel"], b["gravity_dynamic"]
    c, r = b["calibration"], b["reference"]
    particle_skip = [s for s in b["skip"] if "study" not in s]  # the studies' rows follow
    full = selection(b) == "full"
    flags = " --full" * full + " --quick" * b["quick"]
    cmd = {(False, False): "make bench", (True, False): "make bench-full",
           (False, True): "make bench-quick"}.get((full, b["quick"]),
                                                  f"python -m pipelines bench{flags}")
    lines = [
        "# forcecal benchmarks", "",
        f"Produced by `{cmd}` (`python -m pipelines bench{flags}`: "
        + ("every item at full size" if full else "the headline items, some reduced; "
           "`make bench-full` runs every item at full size") + ") "
        f"on {m['date']}, commit `{m['git_commit']}`, {m['cpu_count']} CPUs, {m['platform']}. "
        f"Load average at start {m['load_average_start'][0]:.2f}, at the end "
        f"{m['load_average_end'][0]:.2f}: benchmarks are only meaningful on an otherwise idle "
        "machine; on this shared 2-core machine every time is indicative. Every number comes "
        "from a run of this code (`bench.json`); long results (pipeline runs, FE studies, "
        "reference timings) are cached in `cache/` under the same code and scene "
        "fingerprints, so a rerun after a code change recomputes what the change touches "
        "(the default pipeline run is `make demo`'s when that one is current) and one "
        "without change takes about a minute. " + _duration(b), "",
        "## Goals", "",
    ]
    lines += _goals_section(b)
    lines += [
        "", "## Against the paper", "",
        f"The paper calibrated its 269-node liver in 8 h and ran 3 s of dynamics in 1.3 s on a "
        f"2006 PC. Here: calibration of the {b['scene']} scene ({b['pareto'][0]['connectors']} "
        f"connectors, {b['pareto'][0]['test_points'][0]} calibration points, global + local "
        f"tuning) in {c['wall_s']:.0f} s, {8 * 3600 / c['wall_s']:.0f}x faster; "
        f"{g['duration_s']:g} s of gravity dynamics in {g['particle_s']:.3g} s "
        f"({1.3 * g['duration_s'] / 3 / g['particle_s']:.0f}x faster than the paper's rate; "
        f"{g['steps']} explicit steps of {g['dt_s'] * 1e6:.3g} us), with the error stated "
        f"against the FE ({cell(g['error'])}, relative RMS at the tracked vertex).",
        "", "## Run time vs error", "",
        "![Pareto](pareto.png)", "",
        "Each panel varies one setting of the default scene and times the stage it affects; "
        "green points are Pareto-optimal (no other setting of the panel is both faster and "
        "more accurate), the red star is the default scene. The calibration and mesh panels' "
        "error is the mean of the held-out indentation and relaxation errors of the "
        "calibrated model (relative RMS, docs/results.md 'Error definitions'); their tables also give "
        "the static and dynamic gravity errors ('-' where the gravity stage failed, the "
        "reason below the table). " + _mesh_protocol(b) + " "
        "The calibration panels reuse the default FE reference (a slice of its points for "
        f"fewer calibration points). The particle-dt panel runs {g['duration_s']:g} s of "
        "gravity dynamics of the calibrated model; its Pareto error is the change of the "
        "tracked vertex's history against the smallest step (the error the step controls), "
        "the table also gives the error against the FE. The FE panel is the discretisation "
        "study; its Pareto error is the change of the maximum static sag against P2 on the "
        "uniformly refined mesh (the table also gives the change of the full-depth "
        "indentation forces, which do not converge under refinement: a vertex force, see "
        "docs/limitations.md).",
    ]
    lines += _pareto_section(b)
    lines += ["", "## Kernel throughput", "",
              "Connector updates per second (CPU time of this process, one core) of the "
              "compiled Verlet loop with gravity and Maxwell arms, against the plain-numpy "
              "step (`particle/reference_numpy.py`); uniform parameters.", ""]
    lines += table(["mesh", "connectors", "compiled [updates/s]", "numpy [updates/s]",
                    "ratio"],
                   [[name, row["connectors"], row["compiled_updates_per_s"],
                     row["numpy_updates_per_s"], row["speedup"]]
                    for name, row in (("default liver", k["liver"]),
                                      ("fine liver", k["large"]))])
    lines += ["", f"## {g['duration_s']:g} s of gravity dynamics: particle vs FE", "",
              f"Calibrated particle model, explicit step {g['dt_s'] * 1e6:.3g} us "
              "(particle.dt_safety x the stability limit over the release's strain range), "
              "every vertex recorded every 5 ms, as the gravity stage runs it: "
              f"{g['particle_s']:.3g} s wall ({g['particle_cpu_s']:.3g} s CPU). FE ("
              f"Newmark, dt 5 ms, one rank): {g['fe_s']:.1f} s (from `reference.h5`). Ratio "
              f"**{g['speedup']:.0f}x**. Error of the particle run against the FE: "
              f"{cell(g['error'])} (calibrated), {cell(g['baseline_error'])} (closed-form "
              "baseline); the FE's own discretisation error is the FE panel above.", "",
              "## Skipping what a scene does not need", "",
              "The same explicit run (default liver, linear springs, "
              f"{particle_skip[0]['steps']} steps) with the unneeded terms compiled out (skipped) "
              "and kept at zero (full); CPU seconds.", ""]
    lines += table(["run", "terms it needs", "full [s]", "skipped [s]", "saved"],
                   [[s["scene"], {"viscoelastic": "gravity, arms", "elastic": "gravity",
                                  "free": "none (no load)"}.get(s["scene"], ""),
                     s["full_s"], s["skipped_s"],
                     f"{100 * (1 - s['skipped_s'] / s['full_s']):.0f} %"] for s in particle_skip])
    studied = [s for s in b["skip"] if "study" in s]
    if studied:
        lines += ["", "Whole stages: the scene's `experiments` list (study `experiments`: "
                  "the FE reference and the calibration with the full list against a reduced "
                  "one, each from scratch; wall seconds).", ""]
        lines += table(["stage, experiments kept", "left out", "full [s]", "reduced [s]",
                        "saved"],
                       [[s["scene"], s.get("skipped", ""), s["full_s"], s["skipped_s"],
                         f"{100 * (1 - s['skipped_s'] / s['full_s']):.0f} %"]
                        for s in studied])
    h = b["haptic"]
    lines += ["", "## Haptic latency", "",
              "`HapticSession.step`: 1 ms of simulated time per call (explicit substeps), the "
              "tool particle dragged 5 mm along its normal; wall time per call. `threads` 2: "
              "the opt-in multi-threaded step (`HapticSession(..., threads=2)`, for a dedicated "
              "pair of cores: a busy core stalls it), on the particles renumbered along the "
              "organ's longest axis (`Model.renumbered(spatial_order(model))`) so that the two "
              "threads' connector blocks share few particles.", ""]
    lines += table(["mesh", "connectors", "substeps", "threads", "renumbered", "median [us]",
                    "p99 [us]", "max [us]", "load (1 min)"],
                   [[name, row["connectors"], row["substeps"], row.get("threads", 1),
                     row.get("renumbered", False), row["median_us"], row["p99_us"],
                     row["max_us"], row.get("load_average")] for name, row in h.items()])
    lines += bench_haptic.markdown(b)
    ev = b["evaluators"]
    lines += ["", "## Curve evaluators (calibration's inner loop)", ""]
    lines += table(["curve", "samples", "cold [ms/point]", "warm [ms/point]", "goal [ms]"],
                   [[name, row["samples"], row["cold_ms_per_point"],
                     row["warm_ms_per_point_cpu"], row["goal_ms"]] for name, row in ev.items()])
    lines += ["", "## Calibration", "",
              f"Default scene: {c['wall_s']:.0f} s wall, {c['evaluations']} point-curve "
              "evaluations (from `params.h5`); per stage [s]: "
              + ", ".join(f"{n} {v:.0f}" for n, v in c["stage_times_s"].items()) + ".", "",
              "## FE reference", "",
              f"Full default reference ({r['test_points']} test points x 2 curves + static "
              f"sag + 3 s dynamic run): **" + (
                  "not timed on 1 rank (`make bench-full` does), " if r["wall_s_1rank"] is None
                  else f"{r['wall_s_1rank'] / 60:.1f} min on 1 rank, ")
              + f"{r['wall_s_2ranks'] / 60:.1f} min on 2 ranks** (wall time recorded in "
              "`reference.h5` by the run; sources: "
              + "; ".join(f"{n} rank(s): {v['source']}, {v['measured'][:16]}"
                          + (f", load {v['load_average']:.1f}" if "load_average" in v else "")
                          for n, v in sorted(r["runs"].items())) + "). The two were timed at "
              "different moments; on a shared machine their ratio is not a parallel speed-up "
              "(the default pipeline's run may have overlapped other jobs).", "",
              "## Stability", "",
              "Estimated stability limit of the explicit step (`critical_time_step`, largest "
              "eigenvalue of the kappa-weighted graph Laplacian over strains +-0.5) against "
              "the limit found by bisection (3000 "
              "steps from a perturbed state; blow-up = the integrator's divergence guard); "
              "tested in `tests/test_stability_particle.py`. A ratio <= 1 means the estimate "
              "is safe; its size says how conservative it is.", ""]
    lines += table(["case", "connectors", "estimate [s]", "empirical [s]", "ratio"],
                   [[s["case"], s["connectors"], s["estimate_s"], s["empirical_s"], s["ratio"]]
                    for s in b["stability"]])
    if "scale" in b:  # the scale study
        from pipelines.bench.scale import scale_section
        lines += scale_section(b)
    lines += calibration_methods.markdown(b)
    lines += bench_floor.markdown(b)
    lines += ["", "## Reproduce", "", "```bash", f"{cmd}   # -> {path.parent}/", "```", ""]
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines))
