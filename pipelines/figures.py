"""PNG figures of a run (matplotlib, Agg backend): the paper's Fig. 2 and Fig. 3 and error charts.

* ``calibration.png`` (Fig. 2): (a) force-displacement and (b) relaxation of one
  calibration point - FE, global, calibrated (global + local, or the gradient fit),
  baseline; (c, d) cost per iteration of the global static and relaxation fits; (e) K0 and (f)
  tau1 = b1/k1 per connector.
* ``held_out.png``: the same curves at one held-out point (never fitted).
* ``gravity_static.png`` (Fig. 3): 3-D views of the FE and particle static sag,
  surfaces coloured by |u| on one colour scale.
* ``gravity_dynamic.png`` (Fig. 3e): displacement of the tracked node vs time.
* ``errors.png``: relative RMS error of every test point, calibrated vs baseline.

The example points are the calibration (held-out) point with the *median*
calibrated indentation error, so the figure shows a typical point, not the best.

Only what the scene's experiments produced is drawn: without relaxation the
relaxation panels say so (and tau1 is the uncalibrated initial guess); without
a gravity experiment its figure is not written. A curve, bar or sag a model did not
complete (``report.json`` ``failures``) is not drawn; its legend entry says so.
"""

from __future__ import annotations

import logging
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (the backend must be chosen first)
import numpy as np  # noqa: E402
from matplotlib import cm, colors  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Poly3DCollection  # noqa: E402

from calibration.results import CalibrationResult  # noqa: E402
from forcecal.h5io import Reference, atomic_path  # noqa: E402
from pipelines.gravity import GravityRuns  # noqa: E402

log = logging.getLogger(__name__)

FIGURES = ("calibration.png", "held_out.png", "gravity_static.png", "gravity_dynamic.png",
           "errors.png")
# one style per model, everywhere
STYLE = {"fe": dict(color="black", lw=2.2, label="FE reference"),
         "global": dict(color="tab:orange", lw=1.5, label="particle, global"),
         "calibrated": dict(color="tab:blue", lw=1.5, label="particle, calibrated"),
         "baseline": dict(color="tab:gray", lw=1.3, ls="--",
                          label="particle, baseline (Van Gelder)")}
MM = 1e3


def save_figure(fig: plt.Figure, path: Path, *, tight: bool = True) -> Path:
    """Writes ``fig`` to the PNG ``path`` atomically and closes it; returns ``path``."""
    if tight:  # not for 3-D axes, which place themselves
        fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    return path


def _scale(values: np.ndarray) -> str:
    """'log' when positive values span more than a decade (else log tick labels are unreadable)."""
    return "log" if values.max() > 10 * values.min() > 0 else "linear"


def median_point(errors: np.ndarray, mask: np.ndarray) -> int | None:
    """Index (into the test points) of the point with the median error among ``mask`` (among
    the points the model completed; the first of ``mask`` if it completed none of them, None
    if ``mask`` is empty)."""
    idx = np.nonzero(mask & np.isfinite(errors))[0]
    if not len(idx):
        return int(np.nonzero(mask)[0][0]) if mask.any() else None
    return int(idx[np.argsort(errors[idx])[len(idx) // 2]])


def _curves(ax_force, ax_relax, k: int, reference: Reference, cal: CalibrationResult,
            variants: tuple[str, ...]) -> None:
    """Force-displacement (ax_force) and relaxation (ax_relax) curves of test point index k."""
    ind, rel = reference.indentation, reference.relaxation
    relax = "relaxation" in cal.experiments
    ax_force.plot(MM * ind.displacement, ind.force_normal[k], "o-", ms=3, **STYLE["fe"])
    if relax:
        ax_relax.plot(rel.time, rel.force_normal[k], "o-", ms=3, **STYLE["fe"])
    for v in variants:
        curves = cal.variants[v].curves
        _plot_completed(ax_force, MM * ind.displacement, curves["indentation"][k], v)
        if relax:
            _plot_completed(ax_relax, rel.time, curves["relaxation"][k], v)
    ax_force.set(xlabel="indentation depth [mm]", ylabel="normal force [N]")
    if not relax:
        _not_run(ax_relax)
        ax_force.grid(alpha=0.3)
        ax_force.legend(fontsize=7)
        return
    ax_relax.set(xlabel="time [s]", ylabel="normal force [N]", xscale="log")
    for ax in (ax_force, ax_relax):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)


def _plot_completed(ax, x: np.ndarray, y: np.ndarray, model: str) -> None:
    """``y`` against ``x`` in ``model``'s style, or, when the model did not complete the
    curve (NaN), only a legend entry saying so."""
    if np.all(np.isfinite(y)):
        ax.plot(x, y, **STYLE[model])
    else:
        ax.plot([], [], **{**STYLE[model], "label": f"{STYLE[model]['label']}: did not complete"})


def _not_run(ax, what: str = "relaxation") -> None:
    """An empty panel saying the experiment was not run."""
    ax.text(0.5, 0.5, f"no {what}: not in the scene's experiments", ha="center",
            va="center", transform=ax.transAxes)
    ax.set(xticks=[], yticks=[])


def _cost(ax, cal: CalibrationResult, stage: str, title: str) -> None:
    if stage not in cal.global_fits:
        _not_run(ax)
        ax.set_title(title)
        return
    cost = cal.global_fits[stage].history.iteration_cost
    ax.plot(np.arange(1, len(cost) + 1), cost, color="tab:orange")
    ax.set(xlabel="iteration of the global fit", ylabel="cost G = sum (F_FE - F)^2 [N^2]",
           title=title, yscale=_scale(cost))
    ax.grid(alpha=0.3, which="both")


def _per_connector(ax, values: dict[str, np.ndarray], global_values: np.ndarray, ylabel: str,
                   title: str) -> None:
    """``values`` per connector; the global fit's (E,) values are a line when they are one
    value for all (the paper's uniform set), points when spread by a global shape."""
    x = np.arange(len(values["calibrated"]))
    if "baseline" in values:
        ax.plot(x, values["baseline"], ".", ms=2, color="tab:gray", alpha=0.5,
                label="baseline (Van Gelder)")
    ax.plot(x, values["calibrated"], ".", ms=3, color="tab:blue", label="calibrated")
    if np.ptp(global_values) <= 1e-12 * np.max(np.abs(global_values)):
        ax.axhline(global_values[0], color="tab:orange", lw=1.5, label="global")
    else:
        ax.plot(x, global_values, "_", ms=4, color="tab:orange", label="global (shaped)")
    ax.set(xlabel="connector index", ylabel=ylabel, title=title,
           yscale=_scale(np.concatenate(list(values.values()))))
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7)


def calibration_figure(path: Path, reference: Reference, cal: CalibrationResult) -> Path:
    """The paper's Fig. 2 (module docstring)."""
    err = cal.variants["calibrated"].errors["indentation"]
    k = median_point(err, cal.is_calibration)
    node = int(reference.problem.test_points[k])
    fig, axes = plt.subplots(3, 2, figsize=(11, 12))
    _curves(axes[0, 0], axes[0, 1], k, reference, cal, ("global", "calibrated", "baseline"))
    axes[0, 0].set_title(f"(a) static indentation, calibration node {node}")
    axes[0, 1].set_title(f"(b) relaxation (ramp and hold), node {node}")
    _cost(axes[1, 0], cal, "static", "(c) global static tuning")
    _cost(axes[1, 1], cal, "relaxation", "(d) global relaxation tuning")
    conn = cal.connectors
    _per_connector(axes[2, 0], {v: conn[v].K0 for v in ("calibrated", "baseline")},
                   conn["global"].K0, "K0 [N/m]", "(e) spring stiffness K0 per connector")
    _per_connector(axes[2, 1], {"calibrated": conn["calibrated"].tau1},
                   conn["global"].tau1, "tau1 = b1/k1 [s]",
                   "(f) relaxation time tau1 per connector" + (
                       "" if "relaxation" in cal.experiments else " (not calibrated)"))
    fig.suptitle("Calibration against the FE reference")
    return save_figure(fig, path)


def held_out_figure(path: Path, reference: Reference, cal: CalibrationResult) -> Path | None:
    """Curves of the median held-out point (None if the scene has no held-out points)."""
    err = cal.variants["calibrated"].errors["indentation"]
    k = median_point(err, ~cal.is_calibration)
    if k is None:
        return None
    node = int(reference.problem.test_points[k])
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5))
    _curves(axes[0], axes[1], k, reference, cal, ("global", "calibrated", "baseline"))
    axes[0].set_title(f"static indentation, held-out node {node}")
    axes[1].set_title(f"relaxation, held-out node {node}")
    fig.suptitle("Validation at a held-out point (not used by any fit)")
    return save_figure(fig, path)


def _surface(ax, vertices: np.ndarray, faces: np.ndarray, u: np.ndarray, norm, scale: float,
             title: str) -> None:
    x = vertices + scale * u
    magnitude = MM * np.linalg.norm(u, axis=1)[faces].mean(axis=1)
    poly = Poly3DCollection(x[faces], facecolors=cm.viridis(norm(magnitude)),
                            edgecolors=(0, 0, 0, 0.15), linewidths=0.2)
    ax.add_collection3d(poly)
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    pad = 0.05 * (hi - lo).max()
    ax.set(xlim=(lo[0] - pad, hi[0] + pad), ylim=(lo[1] - pad, hi[1] + pad),
           zlim=(lo[2] - pad, hi[2] + pad), xlabel="x [m]", ylabel="y [m]", zlabel="z [m]",
           title=title)
    ax.set_box_aspect(hi - lo + 2 * pad, zoom=1.1)
    ax.view_init(elev=18, azim=-62)
    ax.locator_params(nbins=4)
    ax.tick_params(labelsize=7)


def gravity_static_figure(path: Path, reference: Reference, gravity: GravityRuns) -> Path:
    """FE vs calibrated particle static sag, deformed surfaces on a shared colour scale (the
    FE's alone when the calibrated model's static sag did not complete)."""
    mesh = reference.problem.mesh
    fe = reference.gravity.static_displacement
    run = gravity.models.get("calibrated")
    panels = [(fe, "FE reference")] + ([] if run is None else [
        (run.static_displacement, "particle, calibrated")])
    peak = max(np.linalg.norm(u, axis=1).max() for u, _ in panels)
    size = float(np.ptp(mesh.vertices, axis=0).max())
    # magnify so the largest sag shows as ~10 % of the organ (1x if it already does)
    scale = max(1.0, round(0.1 * size / peak)) if peak > 0 else 1.0
    norm = colors.Normalize(0.0, MM * peak)
    fig = plt.figure(figsize=(13, 5.5))
    for i, (u, label) in enumerate(panels):
        # the 3-D axes draw their z label outside their box: leave room for it before the next
        ax = fig.add_axes([0.0 + 0.46 * i, 0.02, 0.40, 0.86], projection="3d")
        _surface(ax, mesh.vertices, mesh.surface_faces, u, norm, scale,
                 f"{label}: max sag {MM * np.linalg.norm(u, axis=1).max():.2f} mm")
    if run is None:  # the calibrated panel says how far its static sag got
        carried = [f.reached for f in gravity.failures
                   if f.model == "calibrated" and f.experiment == "gravity_static"]
        ax = fig.add_axes([0.46, 0.02, 0.40, 0.86])
        ax.axis("off")
        ax.text(0.5, 0.5, "particle, calibrated: no static equilibrium"
                + (f"\nbeyond {min(carried):.3g} g" if carried else "")
                + "\n(report.json failures)", ha="center", va="center")
    bar = fig.colorbar(cm.ScalarMappable(norm=norm, cmap="viridis"),
                       cax=fig.add_axes([0.92, 0.2, 0.015, 0.55]))
    bar.set_label("|u| [mm]")
    missing = "" if run is not None else "; the calibrated model did not carry its weight"
    fig.suptitle(f"Static sag under gravity, supported (displacements drawn x{scale:g})"
                 + missing)
    return save_figure(fig, path, tight=False)


def gravity_dynamic_figure(path: Path, reference: Reference, gravity: GravityRuns) -> Path:
    """Vertical displacement and |u| of the tracked node vs time: FE vs particle models."""
    node = reference.problem.tracked_node
    t_fe, u_fe = reference.gravity.time, reference.gravity.displacement[:, node]
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    series = [("fe", t_fe, u_fe)] + [
        (m, gravity.time, None if m not in gravity.models or gravity.models[m].displacement
         is None else gravity.models[m].displacement[:, node]) for m in ("calibrated",
                                                                           "baseline")]
    nothing = np.full(len(t_fe), np.nan)
    for name, t, u in series:  # a release a model did not complete: a legend entry only
        _plot_completed(axes[0], t, nothing if u is None else MM * u[:, 2], name)
        _plot_completed(axes[1], t, nothing if u is None else MM * np.linalg.norm(u, axis=1),
                        name)
    axes[0].set(xlabel="time [s]", ylabel="u_z [mm]", title=f"vertical displacement, node {node}")
    axes[1].set(xlabel="time [s]", ylabel="|u| [mm]", title=f"displacement magnitude, node {node}")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(f"Release under gravity from rest, tracked node {node} (gravity.tracked_node)")
    return save_figure(fig, path)


def errors_figure(path: Path, reference: Reference, cal: CalibrationResult) -> Path:
    """Per-point relative RMS errors, calibration vs held-out points, calibrated vs baseline."""
    nodes = reference.problem.test_points
    n_cal = int(cal.is_calibration.sum())
    x = np.arange(len(nodes))
    n = len(cal.experiments)
    fig, axes = plt.subplots(n, 1, figsize=(max(10, 0.28 * len(nodes)), 3.5 * n), sharex=True,
                             squeeze=False)
    axes = axes[:, 0]
    for ax, e in zip(axes, cal.experiments):
        errors = 100 * np.concatenate([cal.variants[v].errors[e] for v in ("calibrated",
                                                                          "baseline")])
        errors = errors[np.isfinite(errors) & (errors > 0)]
        low, high = (0.5 * errors.min(), 30 * errors.max()) if len(errors) else (0.1, 100.0)
        for offset, v in ((-0.2, "calibrated"), (0.2, "baseline")):
            err = 100 * cal.variants[v].errors[e]
            done = np.isfinite(err)  # a point the model failed has no bar, but a cross
            cal_points, held = done & (x < n_cal), done & (x >= n_cal)
            ax.bar(x[cal_points] + offset, err[cal_points], 0.4, color=STYLE[v]["color"],
                   label=f"{v}, calibration points")
            ax.bar(x[held] + offset, err[held], 0.4, color=STYLE[v]["color"], hatch="//",
                   edgecolor="white", label=f"{v}, held-out points")
            if not done.all():
                ax.plot(x[~done] + offset, np.full(int((~done).sum()), 2 * low), "x",
                        color=STYLE[v]["color"], label=f"{v}, did not complete")
        if n_cal < len(nodes):
            ax.axvline(n_cal - 0.5, color="black", lw=0.8)
        ax.set(ylabel="relative RMS error [%]", yscale="log",
               title=f"{e}: RMS(F_particle - F_FE) / max|F_FE| per test point")
        # log axis set before its limits; room above the bars for the legend
        ax.set_ylim(low, high)
        ax.grid(alpha=0.3, axis="y", which="both")
        ax.legend(fontsize=7, ncol=4)
    axes[-1].set_xticks(x, [str(n) for n in nodes], rotation=90, fontsize=7)
    axes[-1].set_xlabel("test point (vertex id); held-out points right of the line, hatched")
    return save_figure(fig, path)


def write_figures(folder: str | Path, reference: Reference, cal: CalibrationResult,
                  gravity: GravityRuns | None) -> list[Path]:
    """Write every figure of what was run into ``folder``; returns the files written."""
    folder = Path(folder)
    ran = () if gravity is None else gravity.experiments
    written = [calibration_figure(folder / "calibration.png", reference, cal),
               held_out_figure(folder / "held_out.png", reference, cal),
               gravity_static_figure(folder / "gravity_static.png", reference, gravity)
               if "gravity_static" in ran else None,
               gravity_dynamic_figure(folder / "gravity_dynamic.png", reference, gravity)
               if "gravity_dynamic" in ran else None,
               errors_figure(folder / "errors.png", reference, cal)]
    return [p for p in written if p is not None]
