"""``docs/studies.md``: every study with its question, and per committed result its command
and its answer, generated from the result files themselves.

``python -m studies.catalogue [--check]`` writes the page (``--check``: exits 1 if the
committed page differs from what it would write). Each entry of :data:`STUDIES` names its
module, the question it answered, the glob of its committed result files under
``runs/studies/`` and two functions of a result file: the command that writes it (rebuilt
from what the file records: scene, variants, regions, ...) and a one-line answer (its
numbers). A study added to the package needs an entry here (a test checks that every module
has one).
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "studies.md"

Result = dict[str, Any]


@dataclass(frozen=True)
class Study:
    """One study of the page.

    Attributes:
        module: its module in ``studies`` (``python -m studies.<module>``).
        question: what it answered, one sentence.
        results: glob of its committed result files (JSON), relative to the repository.
        command: (result path relative to the repository, its content) -> the command that
            writes it.
        answer: the content of a result file -> its answer in one line of Markdown.
    """
    module: str
    question: str
    results: str
    command: Callable[[str, Result], str]
    answer: Callable[[Result], str]


def pct(value: float | None, digits: int = 1) -> str:
    """A fraction as a percentage (``-`` for None)."""
    return "-" if value is None else f"{100 * value:.{digits}f} %"


def scene_file(name: str) -> str:
    """The scene file of a scene name (the committed scenes are named after their file)."""
    return f"scenes/{name}.toml"


# ---------------------------------------------------------------------------- per study

def fold_cv_command(path: str, r: Result) -> str:
    from studies.fold_cv import DEFAULT_VARIANTS

    variants = {label: v["changes"] for label, v in r["variants"].items()}
    given = "" if variants == DEFAULT_VARIANTS else f" --variants '{json.dumps(variants)}'"
    return f"python -m studies.fold_cv --scene {scene_file(r['scene'])}{given} --out {path}"


def fold_cv_answer(r: Result) -> str:
    scores = ", ".join(f"{label} {pct(v['score'], 2)}" for label, v in r["variants"].items())
    return f"fold error {scores}: **{r['chosen']}**"


def finished_run_command(module: str) -> Callable[[str, Result], str]:
    """The command of a study of a finished run (``--scene`` and ``--out`` only)."""
    return lambda path, r: (f"python -m studies.{module} --scene {scene_file(r['scene'])} "
                            f"--out {path}")


def sag_split_answer(r: Result) -> str:
    rows = {row["label"]: row for row in r["rows"]}
    mixes = [row for label, row in rows.items() if label not in ("global", "calibrated")]
    closest = min(mixes, key=lambda row: abs(row["mean_sag_ratio"] - 1.0))
    return (f"hangs {rows['calibrated']['mean_sag_ratio']:.3f}x the FE (global set "
            f"{rows['global']['mean_sag_ratio']:.3f}x); closest mix: {closest['label']}, "
            f"{closest['mean_sag_ratio']:.3f}x")


def load_softening_answer(r: Result) -> str:
    def shifts(values: list[float]) -> str:
        return " / ".join(f"{100 * v:+.1f}" for v in values)

    rows = r["variants"]
    first = "; ".join(f"{name} {shifts(row['first_mode_shifts'])}" for name, row in rows.items())
    mean = "; ".join(f"{name} {shifts(row['load_shifts'].values())}"
                     for name, row in rows.items())
    strains = r["calibrated_strains"]
    reach = ", ".join(f"[{s['strain'][0]:+.3f}, {s['strain'][1]:+.3f}]" for s in strains)
    ratio = ", ".join(f"{s['stiffness_ratio'][0]:.2f}-{s['stiffness_ratio'][1]:.2f}"
                      for s in strains)
    return (f"lowest mode from rest to about each load: FE {shifts(r['fe_first_mode_shifts'])} "
            f"%; {first} %; the mean mode error's change under each load (points): {mean}; "
            f"the calibrated connectors' strains under the loads {reach}, K(eps)/K0 {ratio}")


def sag_tradeoff_command(path: str, r: Result) -> str:
    return (f"python -m studies.sag_tradeoff --scene {scene_file(r['scene'])} --regions "
            f"{r['regions']} --iterations {r['rows'][-1]['iteration']} --out {path}")


def sag_tradeoff_answer(r: Result) -> str:
    first, last = r["rows"][0], r["rows"][-1]
    return (f"{r['regions']} regions, iteration 0 -> {last['iteration']}: hangs "
            f"{first['mean_sag_ratio']:.3f}x -> {last['mean_sag_ratio']:.3f}x the FE, "
            f"calibration error {pct(first['indentation_calibrated'])} -> "
            f"{pct(last['indentation_calibrated'])}, held-out "
            f"{pct(first['indentation_held_out'])} -> {pct(last['indentation_held_out'])}")


def release_levers_command(path: str, r: Result) -> str:
    figure = Path(path).with_suffix(".png")
    drawn = f" --figure {figure.as_posix()}" if (ROOT / figure).is_file() else ""
    return finished_run_command("release_levers")(path, r) + drawn


def release_levers_answer(r: Result) -> str:
    return "release RMS error: " + ", ".join(f"{row['lever']['label']} {pct(row['rms_error'])}"
                                             for row in r["rows"])


def indenter_radius_command(path: str, r: Result) -> str:
    return (f"python -m studies.indenter_radius --scene {scene_file(r['scene'])} "
            f"--out {path}")


def indenter_radius_answer(r: Result) -> str:
    def spread(rows: list[Result]) -> str:
        errors = [row["held_out_error"] for row in rows if row["held_out_error"] is not None]
        return f"{100 * min(errors):.1f}-{pct(max(errors))}"

    own = [row for row in r["rows"] if row["radius_edges"] == row["fitted_radius_edges"]]
    other = [row for row in r["rows"] if row["radius_edges"] != row["fitted_radius_edges"]]
    return (f"held-out error at the contact size fitted at {spread(own)}, at another size "
            f"{spread(other)}")


def viscoelastic_volume_command(path: str, r: Result) -> str:
    from forcecal.scene import load_scene

    scenes = list(dict.fromkeys(row["scene"] for row in r["rows"]))
    methods = list(dict.fromkeys(row["method"] for row in r["rows"]))
    own = {load_scene(ROOT / scene_file(s)).calibration.method for s in scenes}
    given = "" if set(methods) == own and len(own) == 1 else "".join(
        f" --method {m}" for m in methods)
    return ("python -m studies.viscoelastic_volume"
            + "".join(f" --scene {scene_file(s)}" for s in scenes) + given + f" --out {path}")


def viscoelastic_volume_answer(r: Result) -> str:
    by = {(row["scene"], row["method"], row["volume"]): row["calibrated"] for row in r["rows"]}
    parts = []
    for scene, method in dict.fromkeys((s, m) for s, m, _ in by):
        elastic, relaxing = by[(scene, method, "elastic")], by[(scene, method, "viscoelastic")]
        parts.append(f"{scene} ({method}): release RMS {pct(elastic['rms_error'])} -> "
                     f"{pct(relaxing['rms_error'])}, held-out indentation "
                     f"{pct(elastic['indentation_held_out'])} -> "
                     f"{pct(relaxing['indentation_held_out'])}")
    return "elastic -> viscoelastic volume term: " + "; ".join(parts)


def calibration_time_answer(r: Result) -> str:
    def kind(name: str) -> str:
        row = r["kinds"][name]
        top = ", ".join(f"{k} {v:.1f}" for k, v in list(row["kernels_ms"].items())[:3])
        return (f"{name} ({row['samples']} samples x {r['directions']} directions) "
                f"{row['point_jacobian_ms']:.0f} ms ({top})")
    ap = r["add_partials"]
    parts = []  # in the answer's order
    if "solve_cost" in r:
        sc = r["solve_cost"]
        us = sc["microseconds"]
        most = max(us, key=int)
        parts.append(f"the factorisation's solve ({sc['dofs']} dofs) {us['1']:.0f} us for one "
                     f"right-hand side, {us[str(sc['block'])]:.0f} for {sc['block']}, "
                     f"{us[most]:.0f} for {most}: in blocks of {sc['block']} the outputs' "
                     f"solves would cost {sc['blocked_ratio']:.1f}x")
    if "compression" in r:
        c = r["compression"]
        parts.append(f"a point's rows compressed ({c['rows']} x {c['size']} -> {c['keep']}) "
                     f"{c['compress_ms']:.0f} ms, where the projection through a reversed view "
                     f"of eigh's vectors alone took {c['reversed_view_projection_ms']:.0f} ms "
                     f"(numpy's own loop, not BLAS)")
    if "body_rows_s" in r:
        parts.append(f"the parent's whole-body rows {r['body_rows_s']:.2f} s per linearisation")
    return (f"{r['connectors']} connectors: one point Jacobian, {kind('indentation')}; "
            f"{kind('relaxation')} [ms]; add_partials at {ap['outputs']} outputs "
            f"{ap['gb_per_s']:.0f} GB/s against a plain pass's {ap['memory_gb_per_s']:.0f} GB/s "
            f"over as many bytes" + "".join(f"; {p}" for p in parts))


def haptic_cost_answer(r: Result) -> str:
    rows = r["summary"]["branch"]
    return "median time per 1 ms call: " + ", ".join(
        f"{name} {row['median_us']:.0f} us ({row['substeps']} substep(s))"
        for name, row in rows.items())


def stable_step_gap_answer(r: Result) -> str:
    return "substeps per 1 ms, bound over +-0.5 / over a +-0.05 band / exact at rest (the " \
        "fewest any rigorous bound can give): " + "; ".join(
            f"{row['mesh']} {row['terms']} {row['bound_default_substeps']} / "
            f"{row['bound_band_substeps']} / {row['exact_rest_substeps']}" for row in r["rows"])


def haptic_tail_answer(r: Result) -> str:
    def cell(t: dict) -> str:
        return f"{t['median_us']:.0f} / {t['p99_us']:.0f}"
    return "median / p99 [us] of the step, a compute loop and a pass over the step's working " \
        "set, each of the step's median time: " + "; ".join(
            f"{row['mesh']} ({row['working_set_bytes'] / 1e6:.2f} MB) {cell(row['step'])}, "
            f"{cell(row['compute'])}, {cell(row['memory'])}" for row in r["rows"])


def independent_check_answer(r: Result) -> str:
    if "checks" not in r:
        return (f"no report (exit status {r['exit_status']}): "
                f"{(r.get('error') or '').split(';')[0]}")
    ran = {n: c for n, c in r["checks"].items() if c["status"] != "not_run"}
    better = [n for n, c in ran.items()
              if c["calibrated"] is not None and c["baseline"] is not None
              and (c["calibrated"] >= c["baseline"] if n == "carries_its_weight"
                   else c["calibrated"] <= c["baseline"])]
    cells = ", ".join(f"{n} {pct(c['calibrated'])} ({pct(c['baseline'])})"
                      for n, c in ran.items() if n != "carries_its_weight")
    left = [n for n, c in r["checks"].items() if c["status"] == "not_run"]
    return (f"verdict {'passed' if r['passed'] else 'failed'}; calibrated (baseline): {cells}; "
            f"no worse than the baseline on {len(better)} of {len(ran)} checks run"
            + (f"; not run: {', '.join(left)}" if left else "")
            + (f"; whole-body data fitted: {'+'.join(r['body']['kinds'])}" if r.get("body")
               and r["body"].get("kinds") else ""))


def body_data_command(path: str, r: Result) -> str:
    from studies.body_data import VARIANTS

    scenes = "".join(f" --scene {scene_file(s)}" for s in r["scenes"])
    given = "" if tuple(r["variants"]) == VARIANTS else f" --variants {','.join(r['variants'])}"
    volumes = {row.rpartition(" (")[2].rstrip(")") for e in r["scenes"].values()
               for row in e["rows"] if row.endswith(")")}
    volume = "".join(f" --volume {v}" for v in sorted(volumes))
    return f"python -m studies.body_data{scenes}{given}{volume} --out {path}"


def body_data_answer(r: Result) -> str:
    parts = []
    for scene, entry in r["scenes"].items():
        said = []
        cost = entry.get("fe_cost")
        if cost:
            said.append(f"FE experiment body {cost['body_s']:.0f} s ({pct(cost['share'])} of "
                        "the reference's)")
        if entry["rows"]:
            said.append("held-out indentation / release RMS: " + ", ".join(
                f"{name} {pct(row['calibrated']['indentation_held_out'])} / "
                f"{pct(row['calibrated']['rms_error'])}" for name, row in entry["rows"].items()))
        parts.append(f"{scene}: " + "; ".join(said))
    chosen = (r.get("choice") or {}).get("chosen")
    return "; ".join(parts) + (f"; chosen: **{chosen}**" if chosen else "")


def support_stability_command(path: str, r: Result) -> str:
    from studies.support_stability import FACTORS

    supports = "".join(f" --support {row['rule']['axis']}:{row['rule']['side']}:"
                       f"{row['rule']['tolerance']:g}" for row in r["supports"])
    given = "" if tuple(r["factors"]) == FACTORS else \
        f" --factors {','.join(f'{f:g}' for f in r['factors'])}"
    return (f"python -m studies.support_stability --scene {scene_file(r['scene'])}{supports}"
            f"{given} --out {path}")


def support_stability_answer(r: Result) -> str:
    parts = []
    for row in r["supports"]:
        rule = row["rule"]
        name = f"{rule['axis']} {rule['side']} ({row['n_fixed']} vertices)"
        lowest = row["lowest_eigenvalue_vs_rest"]
        last = row["rows"][-1]
        if row["holds_full_gravity"]:
            parts.append(f"{name} holds 1 g (sag {last['max_sag_mm']:.0f} mm, lowest eigenvalue "
                         f"{min(lowest):.2f}-{max(lowest):.2f} x rest)")
        elif not row["linear_check"]["holds"] or row["sag_check_refusal"]:
            parts.append(f"{name} refused (linear sag {row['linear_check']['linear_sag_mm']:.0f}"
                         f" mm, FE sag {last['max_sag_mm']:.0f} mm at {last['factor']:g} g)")
        else:
            parts.append(f"{name} no equilibrium past {row['reached']:.3g} g (lowest eigenvalue "
                         f"{lowest[-1]:.2f} x rest at {last['factor']:g} g)")
    return "; ".join(parts)


def free_modes_answer(r: Result) -> str:
    parts = []
    for support in ("main", "second", "free"):
        row = next(row for row in r["rows"]
                   if row["support"] == support and row["modulus"] == "instantaneous")
        parts.append(f"{support} {pct(row['calibrated']['mean_abs_frequency_error'])} "
                     f"(baseline {pct(row['baseline']['mean_abs_frequency_error'])})")
    split = r["calibrated_split"]
    kv = "" if split["kv_median_pa"] is None else f", kv median {split['kv_median_pa']:.0f} Pa"
    return (f"calibrated fitting {r['fitted_body_data']}: mean frequency error of the "
            "lowest modes, instantaneous moduli: " + ", ".join(parts)
            + f"; springs {split['spring_ratio_median']:.2f}x the baseline's (median){kv}")


def implicit_haptics_answer(r: Result) -> str:
    parts = []
    for row in r["rows"]:
        e, f = row["explicit"], row["floor"]
        said = (f"{row['mesh']}, {row['terms']}: explicit p99 {e['p99_us']:.0f} us, one solve "
                f"{f['solve']['median_us']:.0f} us + one force pass "
                f"{f['force']['median_us']:.0f} us")
        newmark = next((i for i in row["implicit"] if i["scheme"] == "newmark"), None)
        if newmark is not None:
            said += f"; Newmark p99 {newmark['p99_us']:.0f} us, drag "
            said += (f"{newmark['error_drag']:.1e}" if newmark["diverged"] is None else
                     f"diverged after {newmark['diverged']['call'] * r['period_s']:.1f} s")
            said += (f", release {pct(newmark['error_release'], 2)}"
                     if newmark["release_diverged_s"] is None
                     else f", release diverged after {newmark['release_diverged_s']:.2f} s")
        parts.append(said)
    wins = ", ".join(r["wins"]) or "none"
    return "; ".join(parts) + f"; faster and within the error rules: **{wins}**"


def punch_reach_command(path: str, r: Result) -> str:
    """The recorded command, with ``--out`` where the file is not the default one."""
    return r["command"] + ("" if path == "runs/studies/punch_reach.json" else f" --out {path}")


def punch_reach_answer(r: Result) -> str:
    def scene(path: str, e: Result) -> str:
        s = e["summary"]
        return (f"{Path(path).stem} {s['points_beyond']} of {s['points']} "
                f"(farthest {1e3 * s['max_gap_m']:.1f} mm, {s['max_gap_over_depth']:.1f} x)")
    parts = (["footprints holding particles beyond the punch's depth from its face: "
              + ", ".join(scene(p, e) for p, e in r["scenes"].items())] if r["scenes"] else [])
    if r.get("fe"):
        def run(row: Result) -> str:
            unit = "mm" if row["kind"] == "indentation" else "s"
            scale = 1e3 if row["kind"] == "indentation" else 1.0
            got = (f"{row['normal_force_n']:.3g} N" if row["completed"] else
                   f"failed at {scale * row['reached']:.3g} {unit}" if row["reached"] is not None
                   else "failed")
            return f"{row['kind']} {got} ({row['wall_s']:.0f} s)"
        fe = r["fe"]
        label = {"rule": f"rule {1e3 * fe['radius_m']:.3g} mm",
                 "reach": f"within reach {1e3 * fe['radius_m']:.3g} mm",
                 "radius": f"rule {1e3 * fe['smaller_radius_m']:.3g} mm"}
        parts.append(
            f"FE at vertex {fe['vertex']} of {Path(fe['scene']).stem} (normal force at the "
            "end, or how far it got): " + "; ".join(
                f"{label[name]} ({v['footprint']['nodes']} particles, {v['footprint']['beyond']} "
                f"beyond) " + ", ".join(run(x) for x in v["runs"])
                for name, v in fe["variants"].items()))
    return "; ".join(parts)


def shape_response_command(path: str, r: Result) -> str:
    refined = " --refined" if r.get("refined") else ""
    return (f"python -m studies.shape_response --scene {scene_file(r['scene'])}{refined} "
            f"--out {path}")


def shape_response_answer(r: Result) -> str:
    from studies.shape_response import shift

    def per_load(block: dict, key: str) -> str:
        return " / ".join(f"{100 * shift(load[key], block['rest']):+.1f}" if key in load
                          else "-" for load in block["loads"])

    def rows(block: dict, keys: dict[str, str]) -> str:
        shown = [f"{label} {per_load(block, key)}" for key, label in keys.items()
                 if any(key in load for load in block["loads"])]
        carried = [f"{load['carried']:.2f}" if load.get("carried") is not None else "1"
                   for load in block["loads"]]
        if any(c != "1" for c in carried):
            shown.append(f"carries {' / '.join(carried)} of each load")
        if any("lowest_mode_mac" in load for load in block["loads"]):
            shown.append("lowest mode's MAC with the rest one (loaded) " + " / ".join(
                f"{load['lowest_mode_mac']['loaded']:.2f}" if "lowest_mode_mac" in load
                else "-" for load in block["loads"]))
        if any("min_volume_ratio" in load for load in block["loads"]):
            shown.append("smallest tet V/V0 " + " / ".join(
                f"{load['min_volume_ratio']:.2f}" if "min_volume_ratio" in load else "-"
                for load in block["loads"]))
        return ", ".join(shown)

    fe_keys = {"loaded": "loaded", "without_initial_stress": "without its initial stress",
               "stress_free_on_loaded_shape": "stress-free on the loaded shape"}
    network_keys = {"loaded": "loaded", "without_initial_stress": "without its initial stress",
                    "fe_shape_without_initial_stress": "material part at the FE's shape",
                    "re_derived_on_fe_shape": "re-derived on the FE's shape"}
    parts = [f"FE {name} ({block['element']}, {block['dofs']} dofs): {rows(block, fe_keys)}"
             for name, block in r["fe"].items()]
    parts += [f"{name} network: {rows(block, network_keys)}"
              for name, block in r["networks"].items()]
    why = {"failed": "no equilibrium under the load",
           "fe_shape_failed": "straight tets inverted at the FE's loaded vertices",
           "stress_free_on_loaded_shape_failed": "straight tets inverted at its loaded vertices"}
    failed = sorted({f"{name}: {why[k]}" for group in ("fe", "networks")
                     for name, block in r[group].items() for load in block["loads"]
                     for k in load if k in why})
    note = f" ('-': {'; '.join(failed)})" if failed else ""
    return (f"lowest mode from rest to about each load (%): {'; '.join(parts)}{note}")


def scaled_floor_answer(r: Result) -> str:
    names = {"static_sag": "sag", "release_rms": "release RMS", "period_error": "period",
             "first_peak_error": "first peak", "second_support_static_sag": "second-support sag",
             "second_support_release_rms": "second-support RMS",
             "indentation_held_out": "held-out indentation"}

    def row(values: dict) -> str:
        return ", ".join(f"{label} {pct(values.get(key))}" for key, label in names.items())

    steps = ", ".join(f"{name} {1e3 * dt:.2f} ms"
                      for name, dt in r.get("stable_step_at_rest_s", {}).items())
    return (f"shear moduli x {r['scale']:.3f} (the FE's {len(r['rest_frequencies_fe'])} lowest "
            f"rest modes): " + "; ".join(f"{name}: {row(values)}"
                                          for name, values in r["rows"].items())
            + (f"; explicit stable step at rest: {steps}" if steps else ""))


def body_stiffness_gap_command(path: str, r: Result) -> str:
    levelled = " --levelled" if "levelled_prior" in r else ""
    return (f"python -m studies.body_stiffness_gap --scene {r['scene_file']} --run {r['run']}"
            f"{levelled} --out {path}")


def body_stiffness_gap_answer(r: Result) -> str:
    from studies.body_stiffness_gap import LOWEST

    def lowest(row: dict) -> str:
        return "/".join(f"{100 * e:+.1f}" for e in row["long_term_frequency_errors"][:LOWEST])

    rows = "; ".join(f"{name}: {lowest(row)} % (sag {pct(row['static_sag_error'])}, "
                     f"predicted {pct(row['predicted_sag_error'])})"
                     for name, row in r["rows"].items())
    out = (f"{r['vertices']} vertices, {pct(r['surface_share'], 0)} on the surface, body weight "
           f"{r['body_weight']}; lowest {LOWEST} long-term rest frequencies: {rows}")
    levelled = r.get("levelled_prior")
    if levelled:
        own, new = levelled["own"], levelled["levelled"]
        out += (f"; levelled prior (stiffness x {levelled['factor']:.3f}): CV score "
                f"{own['cv_score']:.4f} -> {new['cv_score']:.4f}, held-out indentation "
                f"{pct(own['indentation_held_out'])} -> {pct(new['indentation_held_out'])}, "
                f"relaxation {pct(own['relaxation_held_out'])} -> "
                f"{pct(new['relaxation_held_out'])}")
    return out


def fit_wall_command(path: str, r: Result) -> str:
    without = " --without-load-strains" if "without_load_strains" in r else ""
    return (f"python -m studies.fit_wall --scene {r['scene_file']} --run {r['run']}{without} "
            f"--out {path}")


def gives_way(rows: list) -> str:
    """What gives way under each load a fit's model carries only up to the fitted load."""
    out = ""
    for k, row in enumerate(rows):
        if not row["at_the_wall"]:
            continue
        out += (f"; at the wall of load {k}: connector {row['connector']} at strain "
                f"{row['connector_strain']:.2f} (FE {row['connector_fe_strain']:.2f}), tangent "
                f"{row['connector_tangent_over_K0']:.2f} K0")
        if "tet" in row:
            out += (f", tet {row['tet']} at volume ratio {row['tet_volume_ratio']:.2g} "
                    f"(FE vertices' {row['tet_fe_volume_ratio']:.3g})")
    return out


def fit_wall_answer(r: Result) -> str:
    def load(k: int, row: dict) -> str:
        wall = " (at the wall)" if row["at_the_wall"] else ""
        return f"load {k} {row['factor']:.3g} x{wall}"

    parts = []
    for name, variant in r["variants"].items():
        parts.append(f"{name}: " + ", ".join(load(k, row)
                                            for k, row in enumerate(variant["loads"])))
    out = f"body data {r['body_data']}; largest load carried: " + "; ".join(parts)
    out += gives_way(r["variants"]["calibrated"]["loads"])
    rule = r.get("without_load_strains")
    if rule:
        own, without = rule["own"], rule["without"]

        def carried(rows: list) -> str:
            return " / ".join(f"{w['factor']:.3g}" for w in rows)

        out += (f"; without the loads' strains in the springs' validity: CV "
                f"score {without['cv_score']:.4f} (with: {own['cv_score']:.4f}), held-out "
                f"indentation {pct(without['indentation_held_out'])} "
                f"({pct(own['indentation_held_out'])}), relaxation "
                f"{pct(without['relaxation_held_out'])} ({pct(own['relaxation_held_out'])}), "
                f"loads carried {carried(rule['without_carries'])} x "
                f"({carried(rule['own_carries'])} x)" + gives_way(rule["without_carries"]))
    return out


STUDIES = (
    Study("fold_cv", "Which calibration setting predicts calibration points it was not "
          "fitted to? (k-fold cross-validation of whole calibrations; the score is the mean "
          "fold error of the indentation and relaxation curves)",
          "runs/studies/fold_cv*.json", fold_cv_command, fold_cv_answer),
    Study("sag_split", "Where does the calibrated model's static sag error come from: which "
          "of its fitted changes (springs, kv), and where? (the mean sag ratio: 1 = hangs as "
          "far as the FE)",
          "runs/studies/sag_split*.json", finished_run_command("sag_split"), sag_split_answer),
    Study("sag_tradeoff", "Could region-wise scalings of the calibrated model fit its punch "
          "curves and hang like the FE at once? (the FE sag as a constraint: a diagnostic, "
          "never a calibration)",
          "runs/studies/sag_tradeoff*.json", sag_tradeoff_command, sag_tradeoff_answer),
    Study("release_levers", "Would a consistent mass or a relaxing volume term, nothing "
          "refitted, bring the calibrated model's gravity release to the FE's?",
          "runs/studies/release_levers*.json", release_levers_command, release_levers_answer),
    Study("indenter_radius", "Does a model calibrated at one contact size (vertex, punches of "
          "1, 1.5, 2 edge lengths) hold at another?",
          "runs/studies/indenter_radius*.json", indenter_radius_command,
          indenter_radius_answer),
    Study("viscoelastic_volume", "Is the calibrated model, refitted with a relaxing "
          "(viscoelastic) volume term, better as a body without losing the surface?",
          "runs/studies/viscoelastic_volume*.json", viscoelastic_volume_command,
          viscoelastic_volume_answer),
    Study("haptic_cost", "What does the volume term, elastic or viscoelastic, cost the haptic "
          "step on the default liver?",
          "runs/studies/haptic_cost*.json", lambda path, r: r["command"], haptic_cost_answer),
    Study("stable_step_gap", "How many haptic substeps could a tighter rigorous stability "
          "bound save: the bound's stable step against the exact one at rest, which no bound "
          "valid at rest can exceed?",
          "runs/studies/stable_step_gap*.json", lambda path, r: r["command"],
          stable_step_gap_answer),
    Study("haptic_tail", "How much of the haptic step's p99 is the machine's: its call times "
          "against compiled loops of the same median time that keep no working set and that "
          "sweep the step's working set?",
          "runs/studies/haptic_tail*.json", lambda path, r: r["command"], haptic_tail_answer),
    Study("independent_check", "Does the README's own-mesh recipe end in a verdict, and beat "
          "the closed-form baseline, on a mesh nobody tuned forcecal on (SOFA's liver, kept "
          "out of the corpus for this)?",
          "runs/studies/independent_check*.json", lambda path, r: r["command"],
          independent_check_answer),
    Study("body_data", "Which whole-body data (natural modes, the weight along the axes "
          "perpendicular to gravity, the modes about those loads), fitted with the surface "
          "curves, to choose on calibration data only, and what do they cost the FE?",
          "runs/studies/body_data*.json", body_data_command, body_data_answer),
    Study("support_stability", "Does a support hold the organ under its whole weight, or does "
          "the FE's static sag stop at a physical limit point (the tangent's lowest eigenvalue "
          "going to zero: the organ tips over on its seat)?",
          "runs/studies/support_stability*.json", support_stability_command,
          support_stability_answer),
    Study("punch_reach", "Does the flat punch hold only the tissue its face reaches (particles "
          "no farther from its face than the depth), and do the FE's punch failures follow "
          "the ones it does not?",
          "runs/studies/punch_reach*.json", punch_reach_command, punch_reach_answer),
    Study("implicit_haptics", "Would one linearised implicit step per 1 ms (Newmark or "
          "HHT-alpha on the tangent factorised at rest) beat the exact explicit haptic step at "
          "large sizes, within 1e-3 of its drag force and 1 % RMS of its release?",
          "runs/studies/implicit_haptics*.json", lambda path, r: r["command"],
          implicit_haptics_answer),
    Study("free_modes", "Do the calibrated model's natural modes match the FE's with a "
          "support it was not fitted with, and without any support (free-free): would "
          "support-free modes tell the calibration what its whole-body data miss?",
          "runs/studies/free_modes*.json", finished_run_command("free_modes"),
          free_modes_answer),
    Study("load_softening", "Does a body load lower the particle model's modes more than the "
          "FE's because of its springs' strain law, or because of its other terms under "
          "load?", "runs/studies/load_softening*.json", finished_run_command("load_softening"),
          load_softening_answer),
    Study("shape_response", "Under its own weight, does the particle model's stiffness follow "
          "the body's change of shape as the FE's does, and is the gap in the stress the load "
          "leaves (initial-stress stiffness) or in the shape it makes?",
          "runs/studies/shape_response*.json", shape_response_command, shape_response_answer),
    Study("scaled_floor", "Would a vertex-only continuum model (the floor's P1 "
          "displacement-pressure tets), its shear stiffness scaled once to the FE's natural "
          "modes, pass the held-out gravity tests better than the calibrated network?",
          "runs/studies/scaled_floor*.json", finished_run_command("scaled_floor"),
          scaled_floor_answer),
    Study("body_stiffness_gap", "Is the calibrated body too soft where its static sag misses, "
          "and is it the surface curves that soften it, or the gradient fit's pull towards the "
          "global fit (a prior levelled to the FE's rest modes instead)?",
          "runs/studies/body_stiffness_gap*.json", body_stiffness_gap_command,
          body_stiffness_gap_answer),
    Study("calibration_time", "Where does the gradient calibration spend its time, kernel by "
          "kernel of a point Jacobian, in a point's compressed rows and in the parent's "
          "whole-body rows, and is its largest kernel bound by arithmetic or by memory?",
          "runs/studies/calibration_time*.json", finished_run_command("calibration_time"),
          calibration_time_answer),
    Study("fit_wall", "Where does the gradient fit stop: at its objective's least, or at a "
          "wall, a fitted body load the model one step further no longer carries, and what "
          "gives way there?",
          "runs/studies/fit_wall*.json", fit_wall_command, fit_wall_answer),
)


def page() -> str:
    """The Markdown of ``docs/studies.md`` from the committed result files."""
    lines = ["# Studies", "",
             "Investigations that answered one question once, unlike the benchmarks "
             "(`make bench`, `make bench-full`), which a user reruns to check speed and error. "
             "Each study is a module of `studies/` with one command; it may use forcecal, "
             "forcecal never uses it. A study of a finished run reads `runs/<scene>/` "
             "(`make demo`'s) unless told `--run DIR`; the numbers below are the committed "
             "result files', made by the code of their day (a rerun on today's code and runs "
             "may differ).", "",
             "Generated by `python -m studies.catalogue` from the files under "
             "`runs/studies/`; a test checks that this page is what it writes.", ""]
    for study in STUDIES:
        paths = sorted(p.relative_to(ROOT).as_posix() for p in ROOT.glob(study.results))
        lines += [f"## {study.module}", "", study.question, "",
                  f"`studies/{study.module}.py`", "",
                  "| result | command | answer |", "|---|---|---|"]
        for path in paths:
            result = json.loads((ROOT / path).read_text())
            lines.append(f"| `{path}` | `{study.command(path, result)}` | "
                         f"{study.answer(result)} |")
        lines.append("")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m studies.catalogue",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true",
                        help=f"exit 1 if {PAGE.relative_to(ROOT)} is not what it would write")
    args = parser.parse_args(argv)
    text = page()
    if args.check:
        if not PAGE.is_file() or PAGE.read_text() != text:
            print(f"error: {PAGE.relative_to(ROOT)} is out of date: run python -m "
                  "studies.catalogue", file=sys.stderr)
            return 1
        return 0
    PAGE.parent.mkdir(parents=True, exist_ok=True)
    PAGE.write_text(text)
    print(f"wrote {PAGE.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
