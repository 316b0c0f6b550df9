"""``haptic scale`` benchmark: the haptic step at 1.4k, 12k and >= 50k connectors, per variant.

``make bench`` measures the first two meshes (:func:`headline_study`: the 12k liver is the
goal's mesh; the 54k one takes about four fifths of the item's time) with
:data:`HEADLINE_CALLS` calls per variant, ``make bench-full`` all three with :data:`CALLS`
(the goals' p99 is over at least :data:`GOAL_CALLS` calls).

``python -m pipelines bench [--full] --only "haptic scale"`` runs it alone (it does not need
the default pipeline run) and writes ``haptic_scale`` into ``bench.json``: one row
per mesh and variant with the latency of :meth:`particle.haptics.HapticSession.step`
(1 ms of simulated time per call) and the variant's error against the float64
default run of the same mesh:

* ``float64``: the default session, ``particle.dt_safety`` x the stability limit
  (the reference of the errors);
* ``renumbered``: the same on the particles renumbered along the longest axis
  (:func:`particle.model.spatial_order`, connectors re-sorted): the physics is
  unchanged, only the force summation order (round-off);
* ``mass-scaled k``: :func:`particle.mass_scaling.scaled_inertia` so that ``k``
  substeps per period (fewer than the default) are within ``dt_safety`` x the
  rigorous limit; the loads keep the physical masses (statics unchanged), the
  transient is slowed where mass was added (``added_mass``: fraction of the free
  mass). Also on the renumbered particles (``mass-scaled k, renumbered``).

Rows of ``terms`` "springs + arms + volume" (:func:`volume_rows`): the same mesh with
the per-tet volume term (:mod:`particle.volume`) at :data:`VOLUME_KV`, the global kv
calibrated on the FE liver, and of ``terms`` "springs + arms + relaxing volume": the term
with Maxwell arms, ``kv`` its long-term stiffness and the arms the scene's Prony split of it
as the benchmark's connectors have (:func:`volume_model`); the variants of each are the float64 default (the reference of their
errors), ``drag's strains`` (the session verified on the strain range the drag needs,
+-:data:`ENVELOPE_MARGIN` x the largest |strain| of the float64 drag rounded up to 0.05,
instead of +-0.5: a larger stable step, as the volume term's bound grows with the faces'
and volumes' possible growth; ``strain_range`` in the row), ``state's strains`` (the
session's per-connector strain bands of half-width :data:`BAND` that follow the state,
``HapticSession(envelope=...)``: ``substeps`` the most of any call, ``recentred`` how often
the bands moved, ``recentre_max_us`` the longest of those calls, which the latencies include;
its release runs at that step, unmonitored, as the bands verify the drag)
and ``mass-scaled 1``/``2``.
``volume_cost`` gives per mesh the time per call with the volume term over springs-only
(the goal: at most :data:`VOLUME_COST_GOAL`, the term may cost half the springs' period again).

The drag: ``calls`` periods (the row's ``calls``: 10 s of device time in the full bench) in
which the tool particle, the top vertex, is pushed 5 mm down over the first 0.25 s
(:data:`RAMP_CALLS`), then held. Errors (relative, as the results' error definitions,
docs/results.md): ``error_drag``, the RMS over the drag's first second
(:data:`ERROR_CALLS` calls: the move and 0.75 s held, whatever the number of calls timed) of
``|F - F_ref|`` over ``max |F_ref|``;
``error_release``, the RMS over 3 s (every 5 ms) of the tracked vertex's
displacement error after a release from rest under :data:`RELEASE_GRAVITY` x the
scene's gravity (``gravity.tracked_node`` rule ``farthest_from_support``) over its
largest displacement, each variant with the step and inertia of its session
(strains verified in the range of the variant's session).

Timings: wall time per call (median, p99, max, and the minimum, the least
disturbed by other processes) and the process CPU time per call over all the drag's calls;
the load average before and after is recorded. Parameters are
:func:`pipelines.bench.particle_engine.scene_model`'s uniform ones.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from forcecal.errors import ParameterError
from forcecal.liver_mesh import generate_liver
from forcecal.point_selection import fixed_nodes
from forcecal.problem import load_mesh, tracked_node_by_rule
from forcecal.scene import Scene
from pipelines.bench.tables import table

log = logging.getLogger(__name__)

# (name, characteristic length [m] of generate_liver; None = the scene's mesh)
MESHES = {False: (("liver", None), ("liver 12k", 0.008), ("liver 54k", 0.0045)),
          True: (("scene mesh", None), ("liver 4k", 0.012))}
HEADLINE_MESHES = 2  # ``make bench``'s: the first of each size's MESHES
CALLS = 10_000  # make bench-full's calls per variant: 10 s of device time
HEADLINE_CALLS = 2_000  # make bench's (and --quick's): 2 s, within the headline's time
GOAL_CALLS = 10_000  # the haptic goals' p99 is of at least this many calls
RAMP_CALLS = 250  # the tool's 5 mm move: over the first 0.25 s, then held
ERROR_CALLS = 1_000  # the drag error's window: the first 1 s (the move and 0.75 s held)
DOWN = np.array([0.0, 0.0, -1.0])
GOAL_US = 100.0
# fraction of the scene's gravity in the release: the uniform benchmark springs carry the full
# weight of the finer livers only beyond the +-0.5 strains the haptic step is verified for
# (54k connectors: -0.55 at half the weight), and one range lets one inertia serve both runs
RELEASE_GRAVITY = 0.25
ERROR_GOAL = 1e-3  # relative error against float64 a faster variant may cost (force rendering)
PERIOD = 1e-3  # s, the device period: one call
# the "drag's strains" variant's verified range: this x the largest |strain| of the float64
# drag (0.28 on the 12k-connector liver, 0.35 on the 54k one), rounded up to 0.05
ENVELOPE_MARGIN = 1.2
ENVELOPE = "drag's strains"
# the "state's strains" variant: HapticSession(envelope=BAND), per-connector strain bands of
# this half-width that follow the state (re-centred as the drag strains the mesh)
BAND = 0.05
FOLLOWING = "state's strains"
SPRINGS, VOLUME = "springs + arms", "springs + arms + volume"
RELAXING = "springs + arms + relaxing volume"
VOLUME_GOAL_US = 200.0  # the p99 goal with a volume term (elastic or relaxing)
# kv [Pa] of the volume rows: the global kv calibrated on the FE liver (runs/liver_volume,
# report.json global_parameters.kv, with K0 = 27 N/m there against the benchmark's 30 N/m)
VOLUME_KV = 8933.75
VOLUME_COST_GOAL = 1.5  # the goal for the volume term's haptic cost over springs-only


def _mesh_model(scene: Scene, length: float | None):
    from pipelines.bench import particle_engine as pb
    # the mesh only: the scene's test points (a covering problem) are not needed here
    mesh = load_mesh(scene) if length is None else generate_liver(length)
    fixed = fixed_nodes(mesh, scene.fixed.axis, scene.fixed.side, scene.fixed.tolerance)
    return pb.scene_model(scene, mesh, fixed), mesh, fixed


def mesh_rows(name: str, model, tool: int, tracked: int, gravity: np.ndarray, *,
              calls: int = CALLS) -> list[dict]:
    """Every springs + arms variant's row on one model, ``calls`` timed calls each (see the
    module docstring)."""
    from particle.model import spatial_order

    order = spatial_order(model)
    renumbered, _ = model.renumbered(order)
    new_id = np.empty(model.n_particles, dtype=np.int64)
    new_id[order] = np.arange(model.n_particles)
    default = _default_substeps(model)
    variants = [Variant("float64"), Variant("renumbered", renumbered=True)]
    for k in range(1, default):
        variants += [Variant(f"mass-scaled {k}", substeps=k),
                     Variant(f"mass-scaled {k}, renumbered", renumbered=True, substeps=k)]
    return _rows(name, SPRINGS, model, (renumbered, new_id), tool, tracked, gravity, variants,
                 calls)


def volume_model(model, kv: float, prony: tuple | None = None):
    """``model`` with the volume term ``kv`` [Pa] on every tet; with ``prony`` = (g (2,), tau
    (2,) [s]) it relaxes: arms ``kv_i = g_i/(1 - g_1 - g_2) kv``, ``bv_i = tau_i kv_i``, the
    split :func:`particle.params.viscoelastic_params` gives the connectors (``kv`` the
    long-term stiffness, ``kv/(1 - g_1 - g_2)`` the instantaneous one)."""
    arms = {}
    if prony is not None:
        (g1, g2), (tau1, tau2) = prony
        k1, k2 = (g / (1.0 - g1 - g2) * kv for g in (g1, g2))
        arms = {"kv1": np.array([k1]), "bv1": np.array([tau1 * k1]), "kv2": np.array([k2]),
                "bv2": np.array([tau2 * k2])}
    return model.with_params(dataclasses.replace(model.params, kv=np.array([float(kv)]),
                                                 **arms))


def volume_rows(name: str, model, tool: int, tracked: int, gravity: np.ndarray,
                kv: float = VOLUME_KV, prony: tuple | None = None, *,
                calls: int = CALLS) -> list[dict]:
    """The variants' rows of one model with the volume term (:func:`volume_model`: ``kv``
    [Pa] on every tet, relaxing with ``prony``), ``calls`` timed calls each: the float64
    default (their errors' reference), the session verified on the strain range the drag
    needs (:data:`ENVELOPE_MARGIN`; a larger stable step), and mass scaling to 1 and 2
    substeps."""
    model = volume_model(model, kv, prony)
    default = _default_substeps(model)
    variants = [Variant("float64"), Variant(ENVELOPE, envelope=True),
                Variant(FOLLOWING, band=BAND)]
    variants += [Variant(f"mass-scaled {k}", substeps=k) for k in (1, 2) if k < default]
    return _rows(name, VOLUME if prony is None else RELAXING, model, None, tool, tracked,
                 gravity, variants, calls)


@dataclasses.dataclass(frozen=True)
class Variant:
    """One haptic variant: its name, on the renumbered particles or not, ``substeps`` per
    period by mass scaling (None: the model's own step), verified on the default strain range
    (+-0.5) or, ``envelope``, on the range the reference's drag needs (:data:`ENVELOPE_MARGIN`)."""
    name: str
    renumbered: bool = False
    substeps: int | None = None
    envelope: bool = False
    band: float | None = None


def _default_substeps(model) -> int:
    """Substeps per period of the float64 default session (the default strain range)."""
    from pipelines.bench import particle_engine as pb
    from particle.haptics import substeps_per_period
    from particle.stability import critical_time_step

    limit = critical_time_step(model)
    return substeps_per_period(PERIOD, pb.DT_SAFETY * limit)


def _rows(name: str, terms: str, model, renumbering, tool: int, tracked: int,
          gravity: np.ndarray, variants: list[Variant], calls: int) -> list[dict]:
    """The rows of ``variants`` on ``model``, ``calls`` timed calls each (at least
    :data:`ERROR_CALLS`, the drag error's window); the first variant is the errors'
    reference. ``renumbering`` = (renumbered model, new particle ids) or None."""
    from pipelines.bench import particle_engine as pb
    from particle.stability import DEFAULT_STRAIN_RANGE, critical_time_step
    from particle.mass_scaling import added_mass_fraction, scaled_inertia

    if calls < ERROR_CALLS:
        raise ParameterError(f"haptic scale: {calls} calls per variant, fewer than the "
                             f"{ERROR_CALLS} of the drag error's window")
    safety = pb.DT_SAFETY
    reference = ref_release = None
    rows = []
    for v in variants:
        strains = DEFAULT_STRAIN_RANGE
        if v.envelope:
            reach = math.ceil(20.0 * ENVELOPE_MARGIN * reference["max_abs_strain"]) / 20.0
            strains = (-reach, reach)
        m, node, tracked_node = ((renumbering[0], int(renumbering[1][tool]),
                                  int(renumbering[1][tracked]))
                                 if v.renumbered else (model, tool, tracked))
        # the session's largest step: the default's, or the period / k with the inertia
        # that makes it stable; the release takes the same step, inertia and strain range
        if v.band is not None:
            step, inertia = PERIOD, None  # the session takes dt_safety x its bands' limit
        elif v.substeps is None:
            step, inertia = safety * critical_time_step(m, strain_range=strains), None
        else:
            step = PERIOD / v.substeps
            inertia = scaled_inertia(m, step / safety, strain_range=strains)
        log.info("haptic scale: %s, %s, %s", name, terms, v.name)
        drag = pb.haptic_drag(m, node, DOWN, step, calls=calls, inertia=inertia,
                              strain_range=strains, envelope=v.band, ramp_calls=RAMP_CALLS)
        if v.band is not None:  # the release at the drag's (smallest) step
            step = drag["dt_s"]
        release = pb.release_history(m, RELEASE_GRAVITY * gravity, step, tracked_node,
                                     inertia=inertia, strain_range=strains,
                                     checked=v.band is None)
        if reference is None:
            reference, ref_release = drag, release
        us = drag["latencies_us"]
        median = float(np.median(us))
        rows.append({
            "mesh": name, "terms": terms, "variant": v.name, "calls": calls,
            "connectors": model.n_connectors,
            "particles": model.n_particles, "tets": 0 if terms == SPRINGS else model.n_tets,
            "strain_range": list(strains),
            "substeps": drag["substeps"], "dt_s": drag["dt_s"], "band": v.band,
            "recentred": drag["recentred"],
            "added_mass": 0.0 if inertia is None else added_mass_fraction(m, inertia),
            "min_us": float(us.min()), "median_us": median,
            "p99_us": float(np.percentile(us, 99)), "max_us": float(us.max()),
            "recentre_max_us": (float(us[drag["recentring"]].max())
                                if drag["recentring"].any() else None),
            "cpu_us": drag["cpu_us"],
            "updates_per_s": model.n_connectors * drag["substeps"] / (1e-6 * median),
            "error_drag": pb.relative_history_error(drag["forces"][:ERROR_CALLS],
                                                    reference["forces"][:ERROR_CALLS]),
            "error_release": pb.relative_history_error(release, ref_release),
            "release_dt_s": step, "load_average": os.getloadavg()[0],
            "goal_us": GOAL_US if terms == SPRINGS else VOLUME_GOAL_US})
    return rows


def volume_cost(rows: list[dict]) -> list[dict]:
    """Per mesh: the volume term's haptic cost, median (and CPU) time per call of the
    springs + arms + volume float64 default over the springs + arms one, and the same ratio
    for the fastest variant of each within :data:`ERROR_GOAL` of its float64 (drag force)."""
    out = []
    for mesh in dict.fromkeys(r["mesh"] for r in rows):
        default = {t: next((r for r in rows if r["mesh"] == mesh and r["terms"] == t
                            and r["variant"] == "float64"), None) for t in (SPRINGS, VOLUME)}
        if None in default.values():
            continue
        best = {t: min((r for r in rows if r["mesh"] == mesh and r["terms"] == t
                        and r["error_drag"] <= ERROR_GOAL), key=lambda r: r["median_us"])
                for t in (SPRINGS, VOLUME)}
        out.append({"mesh": mesh, "connectors": default[SPRINGS]["connectors"],
                    "ratio_median": default[VOLUME]["median_us"] / default[SPRINGS]["median_us"],
                    "ratio_cpu": default[VOLUME]["cpu_us"] / default[SPRINGS]["cpu_us"],
                    "substeps": [default[SPRINGS]["substeps"], default[VOLUME]["substeps"]],
                    "ratio_best_median": best[VOLUME]["median_us"] / best[SPRINGS]["median_us"],
                    "best_variants": [best[SPRINGS]["variant"], best[VOLUME]["variant"]],
                    "goal_ratio": VOLUME_COST_GOAL})
    return out


def study(scene: Scene, cache_folder: Path, quick: bool,
          meshes: int | None = None, calls: int = CALLS) -> dict[str, Any]:
    """The ``haptic_scale`` key of bench.json (rows: see the module docstring) on the first
    ``meshes`` of :data:`MESHES` (None: all), ``calls`` timed calls per variant."""
    import numba

    numba.set_num_threads(1)
    load_start = list(os.getloadavg())
    gravity = np.asarray(scene.gravity.acceleration, dtype=float)
    rows = []
    for name, length in MESHES[quick][:meshes]:
        model, mesh, fixed = _mesh_model(scene, length)
        tool = int(np.argmax(np.where(model.fixed, -np.inf, model.rest_positions[:, 2])))
        tracked = tracked_node_by_rule(mesh, fixed, "farthest_from_support")
        rows += mesh_rows(name, model, tool, tracked, gravity, calls=calls)
        rows += volume_rows(name, model, tool, tracked, gravity, calls=calls)
        rows += volume_rows(name, model, tool, tracked, gravity,
                            prony=(scene.material.prony_g, scene.material.prony_tau),
                            calls=calls)
    return {"haptic_scale": {"rows": rows, "calls": calls, "ramp_calls": RAMP_CALLS,
                             "error_calls": ERROR_CALLS, "depth_m": 0.005,
                             "volume_kv_pa": VOLUME_KV, "volume_cost": volume_cost(rows),
                             "load_average_start": load_start,
                             "load_average_end": list(os.getloadavg()),
                             "goal_us": GOAL_US}}


def headline_study(scene: Scene, cache_folder: Path, quick: bool) -> dict[str, Any]:
    """``make bench``'s item: :func:`study` on the first :data:`HEADLINE_MESHES` meshes,
    :data:`HEADLINE_CALLS` calls per variant."""
    return study(scene, cache_folder, quick, HEADLINE_MESHES, HEADLINE_CALLS)


def goal_rows(b: dict[str, Any]) -> list[list[str]]:
    """Goals-table rows: per mesh above 10k connectors and per terms (springs + arms, with the
    volume term), the one-thread variant with the lowest p99 among those within
    :data:`ERROR_GOAL` of its float64 over the drag (the haptic output), with both of its
    errors; and the volume term's cost (:func:`volume_cost`) on those meshes. A p99 goal
    is met by the p99 of at least :data:`GOAL_CALLS` calls; one within the goal over fewer
    calls (``make bench``'s) is open."""
    h = b.get("haptic_scale")
    if not h:
        return []

    def status(p99: float, goal: float, calls: int) -> str:
        if p99 > goal:
            return "**missed**"
        return "**met**" if calls >= GOAL_CALLS else f"**open** ({calls} calls)"

    out = []
    for mesh, terms in dict.fromkeys((r["mesh"], r.get("terms", SPRINGS)) for r in h["rows"]):
        rows = [r for r in h["rows"] if r["mesh"] == mesh and r.get("terms", SPRINGS) == terms
                and r["error_drag"] <= ERROR_GOAL]
        if not rows or rows[0]["connectors"] < 10_000:
            continue
        best = min(rows, key=lambda r: r["p99_us"])
        with_volume = {SPRINGS: "", VOLUME: ", with the volume term",
                       RELAXING: ", with the relaxing volume term"}[terms]
        goal = best.get("goal_us", GOAL_US)
        calls = best.get("calls", h.get("calls", 0))
        out.append([f"haptic step, {best['connectors']} connectors{with_volume}, 1 thread, "
                    "fastest variant "
                    f"within {ERROR_GOAL:g} of float64 (drag force), p99",
                    f"<= {goal:.0f} us (p99 of >= {GOAL_CALLS} calls)",
                    f"{best['p99_us']:.0f} us (median {best['median_us']:.0f}; {calls} calls; "
                    f"{best['variant']}, {best['substeps']} substep(s); error drag "
                    f"{best['error_drag']:.1e}, release {best['error_release']:.1e})",
                    status(best["p99_us"], goal, calls)])
    for c in h.get("volume_cost", []):
        if c["connectors"] >= 10_000:
            out.append([f"volume term's haptic cost, {c['connectors']} connectors: median time "
                        "per call over springs-only (float64)", f"<= {VOLUME_COST_GOAL:g} x",
                        f"{c['ratio_median']:.1f} x ({c['substeps'][1]} vs {c['substeps'][0]} "
                        f"substeps; fastest variants {c['ratio_best_median']:.1f} x)",
                        "**met**" if c["ratio_median"] <= VOLUME_COST_GOAL else "**missed**"])
    return out


def markdown(b: dict[str, Any]) -> list[str]:
    """The "Haptic variants" section of BENCH.md (empty without a ``haptic_scale`` key)."""
    h = b.get("haptic_scale")
    if not h:
        return []
    lines = ["", "## Haptic variants", "",
             "`HapticSession.step` (1 ms simulated per call, one thread) per mesh and variant "
             "(`pipelines/bench/haptic.py`, `python -m pipelines bench [--full] --only \"haptic "
             "scale\"`): "
             f"a {h['calls']}-call drag of the top vertex 5 mm down over the first "
             f"{h.get('ramp_calls', h['calls'] // 4)} calls, then held, every call timed. "
             "Errors against the float64 default of the same mesh: `drag`, the tool force over "
             f"the first {h.get('error_calls', h['calls'])} calls; "
             "`release`, the tracked vertex over 3 s of gravity release (relative RMS). "
             "`mass-scaled k`: inertia added where the stiffness limits the step "
             "(`particle.mass_scaling.scaled_inertia`) so that k substeps per ms are within "
             "`dt_safety` x the rigorous limit; `added mass` is the fraction of the free mass "
             f"added. The release is under {RELEASE_GRAVITY:g} x gravity (the uniform "
             "benchmark springs do not carry the finer livers' full weight within the +-0.5 "
             "strains the haptic step is verified for), with each variant's step and inertia."
             f" `springs + arms + volume`: the volume term at kv = {h.get('volume_kv_pa', 0):g} "
             "Pa (the global kv calibrated on the FE liver), its errors against its own "
             "float64 row; `springs + arms + relaxing volume`: the same kv as the term's "
             "long-term stiffness, with Maxwell arms of the connectors' Prony split; "
             "`drag's strains`: the session verified on "
             f"+-{ENVELOPE_MARGIN:g} x the largest strain of the float64 drag (rounded up to "
             "0.05) instead of +-0.5; `state's strains`: per-connector bands of half-width "
             f"{BAND:g} that follow the state (`HapticSession(envelope=...)`), re-centred "
             "(`recentred` times, the longest such call under `re-centre [us]`, included in "
             "the other times). updates/s counts connectors only."
             " min and CPU time per call are the "
             "measures least affected by other processes. Load average "
             f"{h['load_average_start'][0]:.1f} at the start, {h['load_average_end'][0]:.1f} "
             "at the end.", ""]
    lines += table(["mesh", "connectors", "terms", "variant", "substeps", "added mass",
                    "min [us]", "median [us]", "p99 [us]", "max [us]", "CPU [us/call]",
                    "recentred", "re-centre [us]", "updates/s", "error drag", "error release"],
                   [[r["mesh"], r["connectors"], r.get("terms", SPRINGS), r["variant"],
                     r["substeps"],
                     f"{100 * r['added_mass']:.2g} %",
                     r["min_us"], r["median_us"], r["p99_us"], r["max_us"], r["cpu_us"],
                     r.get("recentred") or "", r.get("recentre_max_us") or "",
                     r["updates_per_s"], r["error_drag"], r["error_release"]]
                    for r in h["rows"]])
    if h.get("volume_cost"):
        lines += ["", f"The volume term's haptic cost (kv = {h['volume_kv_pa']:g} Pa on every "
                  "tet): time per call with it over springs-only, float64 defaults "
                  "(median and CPU time) and the fastest variant of each within "
                  f"{ERROR_GOAL:g} of its float64 (drag force); goal <= "
                  f"{VOLUME_COST_GOAL:g}x.", ""]
        lines += table(["mesh", "connectors", "substeps (springs, volume)", "ratio median",
                        "ratio CPU", "ratio fastest", "fastest variants"],
                       [[c["mesh"], c["connectors"], "{}, {}".format(*c["substeps"]),
                         f"{c['ratio_median']:.2f}", f"{c['ratio_cpu']:.2f}",
                         f"{c['ratio_best_median']:.2f}", "; ".join(c["best_variants"])]
                        for c in h["volume_cost"]])
    return lines
