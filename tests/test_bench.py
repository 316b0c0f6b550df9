"""The benchmark's own logic (no timing is asserted): Pareto fronts, derived scenes, sliced
references, recognising a resumed reference run."""
import json
import shutil

import numpy as np
import pytest

from forcecal.errors import ParameterError
from forcecal.scene import load_scene, replace
from pipelines.bench.items import _complete_run_seconds
from pipelines.bench.configs import (Config, derived_scene, pareto_front, scene_toml,
                                     sliced_reference)
from tests.conftest import ROOT, SCENES
from tests.test_h5io import _fake_reference


def test_pareto_front_keeps_exactly_the_undominated_points():
    rows = [{"wall_s": t, "errors": {"overall": e}} for t, e in
            [(1.0, 0.5), (2.0, 0.2), (3.0, 0.3), (4.0, 0.1), (2.0, 0.2), (0.5, 0.9)]]
    # (3, 0.3) is beaten by (2, 0.2); the repeated (2, 0.2) does not dominate its twin
    assert pareto_front(rows) == [True, True, False, True, True, True]


def test_derived_scene_round_trips_through_toml(tmp_path):
    base = load_scene(SCENES / "tiny.toml")
    changes = {"calibration": {"local": False, "static_max_evaluations": 7},
               "test_points": {"calibration": [3, 5, 8]}}
    scene = derived_scene(base, "bench-x", changes, tmp_path)
    assert scene.path == tmp_path / "scene.toml" and scene.name == "bench-x"
    assert scene.calibration.local is False and scene.calibration.static_max_evaluations == 7
    assert scene.test_points.calibration == (3, 5, 8)
    assert not scene.outputs.figures and not scene.outputs.fields
    for section in ("mesh", "material", "fixed", "indentation", "relaxation", "gravity", "fe",
                    "particle"):
        assert scene.fingerprint(section) == base.fingerprint(section), section
    mtime = scene.path.stat().st_mtime_ns
    derived_scene(base, "bench-x", changes, tmp_path)  # unchanged: the file is not rewritten
    assert scene.path.stat().st_mtime_ns == mtime
    assert "[calibration]" in scene_toml(json.loads(json.dumps(base.to_dict(), default=list)))


def test_sliced_reference_keeps_the_curves_of_its_points(tmp_path, liver_scene, liver_problem):
    reference = _fake_reference(liver_problem, liver_scene.material)
    picked = [int(p) for p in liver_problem.calibration[[0, 5, 9]]]
    held = [int(p) for p in liver_problem.held_out]
    config = Config("calibration points", "3 points", {},
                    {"test_points": {"calibration": picked, "held_out": held}}, reference="slice")
    scene = derived_scene(liver_scene, "bench-slice", config.changes, tmp_path)
    sliced = sliced_reference(reference, scene)
    np.testing.assert_array_equal(sliced.problem.calibration, picked)
    np.testing.assert_array_equal(sliced.problem.held_out, liver_problem.held_out)
    rows = [0, 5, 9] + list(range(len(liver_problem.calibration), len(liver_problem.test_points)))
    np.testing.assert_array_equal(sliced.indentation.force, reference.indentation.force[rows])
    np.testing.assert_array_equal(sliced.relaxation.force_normal,
                                  reference.relaxation.force_normal[rows])
    assert sliced.gravity is reference.gravity
    assert sliced.meta["scene_fingerprint"] != reference.meta["scene_fingerprint"]


def test_a_sliced_reference_is_adopted_instead_of_recomputed(tmp_path, liver_scene,
                                                            liver_problem):
    """The slice records the experiment keys a run of its own scene would record (its FE
    curves equal such a run's, each work item depending on its own point only), so the
    pipeline adopts it; the unsliced file holds another list of points and is not."""
    from forcecal.h5io import write_reference
    from pipelines.runners.common import REFERENCE, Context
    from pipelines.runners.reference import adopt_reference
    from reference_fe.keys import experiment_keys

    mesh = liver_problem.mesh.fingerprint()
    reference = _fake_reference(liver_problem, liver_scene.material)
    reference.meta["experiment_keys"] = json.dumps(experiment_keys(liver_scene, mesh))
    picked = [int(p) for p in liver_problem.calibration[[0, 5, 9]]]
    scene = derived_scene(liver_scene, "bench-slice", {"test_points": {
        "calibration": picked, "held_out": [int(p) for p in liver_problem.held_out]}}, tmp_path)
    context = Context(scene=scene, out=tmp_path, progress=False, ranks=1)
    write_reference(tmp_path / REFERENCE, reference)
    assert not adopt_reference(context, mesh)
    write_reference(tmp_path / REFERENCE, sliced_reference(reference, scene))
    assert adopt_reference(context, mesh)


@pytest.mark.parametrize("total, complete", [(100.0, True), (40.0, False)])
def test_a_resumed_reference_run_is_not_taken_as_a_wall_time(liver_scene, liver_problem, total,
                                                             complete):
    """Items computed 2 x 80 s of CPU on 2 ranks: a 100 s run did them all, a 40 s run cannot
    have (it resumed from checkpoints of an earlier one)."""
    reference = _fake_reference(liver_problem, liver_scene.material)
    reference.meta.update(n_ranks=2, timings_s=json.dumps(
        {"mesh": 1.0, "indentation": 40.0, "relaxation": 80.0, "gravity_static": 10.0,
         "gravity_dynamic": 30.0, "total": total}))
    assert _complete_run_seconds(reference) == ((2, total) if complete else None)


def _row(axis, label, wall, error, default=False):
    return {"axis": axis, "label": label, "wall_s": wall, "errors": {"overall": error},
            "default": default}


def test_the_default_row_is_on_the_front_only_if_it_is_on_every_axis_front():
    from pipelines.bench.configs import mark_fronts
    rows = [_row("default", "liver", 10.0, 0.2, True),
            _row("budget", "x1", 10.0, 0.2, True), _row("budget", "x0.5", 5.0, 0.3),
            _row("local", "on", 10.0, 0.2, True), _row("local", "off", 5.0, 0.3)]
    mark_fronts(rows)
    assert [r["on_front"] for r in rows] == [True, True, True, True, True]
    rows[-1]["errors"]["overall"] = 0.1  # "off" now dominates the default on its axis
    mark_fronts(rows)
    assert [r["on_front"] for r in rows] == [False, True, True, False, True]


def _bench():
    return {"kernel": {"connectors": 1400, "updates_per_s": 2e8, "numpy_ratio": 50.0},
            "gravity_dynamic": {"particle_s": 0.04, "fe_s": 240.0, "speedup": 6000.0,
                                "error": 0.27},
            "calibration": {"wall_s": 83.0, "evaluations": 15000},
            "reference": {"wall_s_1rank": 800.0, "wall_s_2ranks": 400.0},
            "pareto": [{"config": {}, "stage": "calibration", "wall_s": 83.0,
                        "errors": {"overall": 0.13}},
                       {"config": {"local": False}, "stage": "calibration", "wall_s": None,
                        "errors": None, "failed": "ConvergenceError: ..."}],
            "skip": [{"scene": "elastic", "full_s": 0.05, "skipped_s": 0.03}]}


@pytest.mark.parametrize("damage, message", [
    (lambda b: b["kernel"].pop("numpy_ratio"), "kernel.numpy_ratio is missing"),
    (lambda b: b.pop("reference"), "reference.wall_s_1rank is missing"),
    (lambda b: b["calibration"].update(wall_s=float("nan")), "calibration.wall_s = nan"),
    (lambda b: b["pareto"][0].update(wall_s=None), r"pareto\[0\].wall_s = None"),
    (lambda b: b["pareto"][0].pop("stage"), r"pareto\[0\].stage is missing"),
    (lambda b: b.update(skip=[]), "skip must be a non-empty list"),
    (lambda b: b["skip"][0].update(skipped_s="fast"), r"skip\[0\].skipped_s = 'fast'"),
])
def test_check_bench_refuses_missing_keys_and_non_finite_numbers(damage, message):
    from forcecal.errors import DataFileError
    from pipelines.bench.driver import check_bench
    bench = _bench()
    check_bench(bench)
    damage(bench)
    with pytest.raises(DataFileError, match=message):
        check_bench(bench)


def test_the_punch_scenes_whole_body_calibration_has_a_goal_row():
    """The liver punch's calibration time goal (<= 120 s) is read off its punch + whole-body
    row of the calibration methods item: met at the goal, missed above it or when that row
    failed, and no row before the item has run."""
    from pipelines.bench.report import _punch_calibration_rows

    def bench(**body):
        other = {"scene": "liver_punch", "model": "springs", "method": "gradient",
                 "calibration_s": 30.0}
        return {"calibration_methods": [other, {"scene": "liver_punch",
                                                "model": "springs + relaxing volume",
                                                "method": "gradient + body", **body}]}

    (row,) = _punch_calibration_rows(bench(calibration_s=120.0))
    assert row == ["calibration, liver_punch scene, springs + relaxing volume, gradient + body, "
                   "2 cores", "<= 120 s", "120 s", "**met**"]
    assert _punch_calibration_rows(bench(calibration_s=121.0))[0][2:] == ["121 s", "**missed**"]
    assert _punch_calibration_rows(bench(failed="no equilibrium"))[0][2:] == [
        "failed", "**missed**"]
    assert _punch_calibration_rows({"calibration_methods": []}) == []
    assert _punch_calibration_rows({}) == []


def test_the_committed_bench_has_every_fixed_key_and_the_docs_show_its_goals():
    from pipelines.bench.driver import read_bench
    from pipelines.bench.report import goals_markdown
    bench = read_bench(ROOT / "runs" / "bench" / "bench.json")
    assert goals_markdown(bench) in (ROOT / "docs" / "benchmarks.md").read_text()


def test_read_bench_refuses_a_damaged_file(tmp_path):
    from forcecal.errors import DataFileError
    from pipelines.bench.driver import read_bench
    (tmp_path / "bench.json").write_text('{"kernel": ')
    with pytest.raises(DataFileError, match="cannot read"):
        read_bench(tmp_path / "bench.json")
    (tmp_path / "bench.json").write_text("[1, 2]")
    with pytest.raises(DataFileError, match="not a bench.json"):
        read_bench(tmp_path / "bench.json")


def test_haptic_scale_rows_state_each_variants_substeps_and_error():
    """The haptic variants benchmark on a small box whose limit needs 3 substeps per ms: the
    renumbered variant differs by round-off only, the mass-scaled ones take fewer substeps
    with their added mass and error stated; each row records its number of timed calls,
    which may not be fewer than the drag error's window."""
    from pipelines.bench.haptic import ERROR_CALLS, mesh_rows
    from tests.particle_models import box_model, top_centre

    model = box_model((3, 3, 2), K0=200.0)
    args = ("box", model, top_centre(model), int(model.free_nodes[-1]),
            np.array([0.0, 0.0, -9.81]))
    rows = {r["variant"]: r for r in mesh_rows(*args, calls=ERROR_CALLS + 200)}
    assert {r["calls"] for r in rows.values()} == {ERROR_CALLS + 200}
    with pytest.raises(ParameterError, match="fewer than the 1000 of the drag error's window"):
        mesh_rows(*args, calls=ERROR_CALLS - 1)
    assert set(rows) == {"float64", "renumbered", "mass-scaled 1", "mass-scaled 1, renumbered",
                         "mass-scaled 2", "mass-scaled 2, renumbered"}
    assert rows["float64"]["substeps"] == 3 and rows["float64"]["error_drag"] == 0.0
    assert rows["renumbered"]["error_drag"] < 1e-12 and rows["renumbered"]["error_release"] < 1e-12
    for k in (1, 2):
        row = rows[f"mass-scaled {k}"]
        assert row["substeps"] == k and row["added_mass"] > 0.0
        assert 0.0 < row["error_drag"] < 1.0 and 0.0 < row["error_release"] < 1.0
        assert rows[f"mass-scaled {k}, renumbered"]["error_drag"] == pytest.approx(
            row["error_drag"], rel=1e-6)
    assert rows["mass-scaled 1"]["added_mass"] > rows["mass-scaled 2"]["added_mass"]


def test_cold_times_keep_the_earlier_cold_time_of_an_item_that_reused_work():
    import logging

    from pipelines.bench.driver import ReuseCounter, cold_times

    counter = ReuseCounter()
    logger = logging.getLogger("pipelines.stages")
    logger.addHandler(counter)
    try:
        logger.warning("reference up to date, skipped (inputs and outputs match x)")
        logger.warning("reference running: no cache record")
    finally:
        logger.removeHandler(counter)
    assert counter.hits == 1
    previous = {"item_s_cold": {"a": 100.0}}
    assert cold_times({"a": 2.0, "b": 30.0}, {"a"}, previous) == {"a": 100.0, "b": 30.0}
    assert cold_times({"a": 2.0}, {"a"}, {}) == {"a": None}  # reused, cold time never measured


def test_a_cold_bench_needs_an_empty_cache_and_adopts_nothing_from_runs(tmp_path):
    from forcecal.errors import ForcecalError
    from pipelines.bench.driver import run_bench
    from pipelines.bench.items import ROOT, default_folder, runs_source, seed_default

    out = tmp_path / "bench"
    (out / "cache" / "runs").mkdir(parents=True)
    (out / "cache" / "runs" / "old.json").write_text("{}")
    with pytest.raises(ForcecalError, match="holds earlier work"):
        run_bench(out, quick=True, cold=True)
    with pytest.raises(ForcecalError, match="--only"):
        run_bench(out, quick=True, cold=True, only=("stability limits",))
    cache = tmp_path / "cold" / "cache"
    assert runs_source(cache, "liver") == ROOT / "runs" / "liver"
    cache.mkdir(parents=True)
    (cache / "COLD").write_text("")
    assert runs_source(cache, "liver") is None
    # a cold cache's default run is not seeded from runs/<scene>/ even when that one finished
    seed_default(load_scene(SCENES / "tiny.toml"), cache)
    assert not default_folder(cache).exists()


def test_a_finished_run_seeds_a_folder_once(tmp_path):
    """Seeding copies a finished run's files and stage records (the pipeline's cache then
    decides what is current) unless the folder's own run finished later."""
    import os

    from pipelines.bench.items import SEED_FILES, seed_folder

    source, folder = tmp_path / "default", tmp_path / "row"
    assert not seed_folder(source, folder)  # nothing finished there
    (source / "cache").mkdir(parents=True)
    for name in SEED_FILES:
        (source / name).write_text(name)
    for record in ("calibrate.json", "report.json"):
        (source / "cache" / record).write_text(record)
    assert seed_folder(source, folder)
    assert all((folder / name).read_text() == name for name in SEED_FILES)
    assert (folder / "cache" / "calibrate.json").read_text() == "calibrate.json"
    (folder / "cache" / "report.json").write_text("the row's own report")
    later = (source / "cache" / "report.json").stat().st_mtime + 10
    os.utime(folder / "cache" / "report.json", (later, later))
    assert not seed_folder(source, folder)  # the row's own run is newer: kept
    assert (folder / "cache" / "report.json").read_text() == "the row's own report"


def test_the_experiments_study_needs_the_default_run_for_its_full_list(tmp_path):
    from forcecal.errors import ForcecalError
    from pipelines.bench.experiments import full_list

    with pytest.raises(ForcecalError, match="no finished default run"):
        full_list(load_scene(SCENES / "tiny.toml"), tmp_path / "runs" / "default")


def test_calibration_methods_front_is_per_scene_and_skips_failed_rows():
    from pipelines.bench.calibration_methods import held_out_error, mark_front

    def row(scene, held, static, cal, p99):
        return {"scene": scene, "calibration_s": cal, "haptic": {"p99_us": p99},
                "errors": {"indentation_held_out": held, "relaxation_held_out": held,
                           "gravity_static": static}}

    rows = [row("a", 0.10, 0.05, 100.0, 20.0),   # dominated by the next one
            row("a", 0.08, 0.05, 100.0, 20.0),
            row("a", 0.12, 0.02, 300.0, 50.0),   # worse held-out, better sag: kept
            row("b", 0.20, 0.10, 500.0, 90.0),   # alone in its scene: kept
            {"scene": "a", "model": "springs", "method": "paper", "failed": "diverged"}]
    mark_front(rows)
    assert [r["front"] for r in rows] == [False, True, True, True, False]
    assert held_out_error({"indentation_held_out": 0.04, "relaxation_held_out": 0.06}) == \
        pytest.approx(0.05)
    assert held_out_error({"indentation_held_out": 0.04}) is None


def test_calibration_methods_has_the_punch_and_whole_body_row(tmp_path, monkeypatch):
    """The punch scene gets the punch + whole-body method's row as it ships it (its volume
    term, the gradient fit with its body_data and the experiment body) after its four, which
    fit the surface curves only (body left out), on the reference of the rows before it; the
    bench scene keeps its four rows."""
    from pipelines.bench import calibration_methods as cm
    from pipelines.bench import items
    from pipelines.bench.configs import derived_scene

    calls = []

    def fake_row(scene, model, volume, method, folder, reference_from, current):
        calls.append((scene.name, model, volume, method, folder.name, reference_from))
        return {"scene": scene.name, "model": model, "method": method, "failed": "not run"}

    monkeypatch.setattr(cm, "run_row", fake_row)
    monkeypatch.setattr(items, "runs_source", lambda cache, name: None)
    monkeypatch.setattr(items, "default_folder", lambda cache: cache / "runs" / "default")
    monkeypatch.setattr(items, "seed_folder", lambda source, folder: None)
    rows = cm.study(load_scene(SCENES / "tiny.toml"), tmp_path, quick=False)
    punch = [c for c in calls if c[0] == "liver_punch"]
    assert len(calls) == 9 and len(punch) == 5 and len(rows["calibration_methods"]) == 9
    punch_scene = load_scene(cm.PUNCH_SCENE)
    model, volume, calibration, experiments = cm.body_row(punch_scene)
    assert punch[-1][1:5] == (model, volume, cm.BODY_METHOD, "volume-gradient-body")
    assert (model, volume) == ("springs + relaxing volume", "viscoelastic")
    body = derived_scene(punch_scene, "x", {"particle": {"volume": volume},
                                            "calibration": calibration},
                         tmp_path / "x", experiments=experiments)
    assert body.runs("body") and body.calibration.body_data == punch_scene.calibration.body_data
    assert body.calibration.method == "gradient" and body.particle.volume == "viscoelastic"
    surface = derived_scene(punch_scene, "y", {}, tmp_path / "y",
                            experiments=cm.surface_only(punch_scene))
    assert not surface.runs("body") and surface.runs("second_support")
    assert cm.surface_only(load_scene(SCENES / "tiny.toml")) is None
    tiny = replace(load_scene(SCENES / "tiny.toml"), calibration={"method": "gradient"})
    assert cm.body_row(tiny)[1:] == (True, {"method": "gradient", "body_data": "loads+modes"},
                                     (*tiny.experiments, "body"))


def test_a_partial_run_is_refused_before_it_runs_without_a_whole_run_of_its_kind(tmp_path):
    """``--only`` completes a whole run's bench.json: into a folder without one, or with one
    of another size or scene, or with a corrupt or incomplete one, it is refused up front
    (it used to run its items and then fail the file check, losing their work)."""
    from forcecal.errors import ForcecalError
    from pipelines.bench.driver import run_bench

    out = tmp_path / "bench"
    with pytest.raises(ForcecalError, match="does not exist; --only reruns"):
        run_bench(out, quick=True, only=("stability limits",))
    out.mkdir()
    (out / "bench.json").write_text("{")  # cut short
    with pytest.raises(ForcecalError, match="cannot read .*bench.json"):
        run_bench(out, quick=True, only=("stability limits",))
    (out / "bench.json").write_text(json.dumps({"scene": "tiny", "quick": True}))
    with pytest.raises(ForcecalError, match="bench.json: .* is missing"):  # not a whole run
        run_bench(out, quick=True, only=("stability limits",))
    shutil.copy(ROOT / "runs" / "bench" / "bench.json", out / "bench.json")
    with pytest.raises(ForcecalError, match="is a full run of scene 'liver', this one a "
                                            "--quick run of 'tiny'"):
        run_bench(out, quick=True, only=("stability limits",))
    assert sorted(p.name for p in out.iterdir()) == ["bench.json"]  # nothing ran


def test_a_partial_run_keeps_the_full_runs_machine_and_records_its_own():
    """``--only`` keeps every key of the full run, its machine (date, commit) included, and
    records its own machine with the items it ran; an item rerun again moves to the new entry."""
    from pipelines.bench.driver import partial_bench

    full = {"machine": {"date": "d0", "git_commit": "c0"}, "scale": [1], "item_s": {"a": 1.0}}
    first = partial_bench(full, {"date": "d1", "git_commit": "c1"}, ("scale", "haptic"),
                          "liver", False)
    assert first["machine"] == full["machine"] and first["scale"] == [1]
    assert first["reruns"] == [{"items": ["scale", "haptic"], "date": "d1", "git_commit": "c1"}]
    second = partial_bench(first, {"date": "d2", "git_commit": "c2"}, ("scale",), "liver", False)
    assert second["machine"] == full["machine"]
    assert second["reruns"] == [{"items": ["haptic"], "date": "d1", "git_commit": "c1"},
                                {"items": ["scale"], "date": "d2", "git_commit": "c2"}]
    assert partial_bench(second, {"date": "d3", "git_commit": "c3"}, ("haptic", "scale"),
                         "liver", False)["reruns"] == [
        {"items": ["haptic", "scale"], "date": "d3", "git_commit": "c3"}]


def test_a_partial_run_records_the_default_run_it_brings_up_to_date():
    """``--only "calibration methods"`` also reruns the default pipeline run (its calibration
    block and goals are rewritten), so both are listed as this run's items, in the bench's
    order; an item that needs no default run is listed alone."""
    from pipelines.bench.driver import selected_items

    names = ["default pipeline run", "scale", "calibration methods", "volume term"]
    assert selected_items(names, ("calibration methods",)) == ("default pipeline run",
                                                               "calibration methods")
    assert selected_items(names, ("scale",)) == ("scale",)


def test_make_bench_runs_the_headline_items_and_bench_full_every_item():
    """``make bench`` (headline) runs the speed and error axes in the bench's order, leaving
    the long items to ``make bench-full``; every item in a module of its own names a function
    of the same signature in both selections."""
    import inspect

    from forcecal.errors import ForcecalError
    from pipelines.bench.driver import ITEMS, ModuleItem, item_run, items_of

    assert [i.name for i in items_of(True)] == [i.name for i in ITEMS]
    assert [i.name for i in items_of(False)] == [
        "default pipeline run", "run time vs error", "reference timings", "particle engine",
        "stability limits", "haptic scale", "fe_convergence", "scale", "volume term"]
    assert {i.name for i in ITEMS} - {i.name for i in items_of(False)} == {
        "experiments", "scale reference", "calibration methods", "discretisation floor"}
    reduced = {i.name for i in ITEMS if i.headline not in (None, i.full)}
    assert reduced == {"run time vs error", "reference timings", "haptic scale",
                       "fe_convergence", "scale"}
    for item in ITEMS:  # function(scene, cache folder, quick)
        for run in (item.full, item.headline):
            if isinstance(run, ModuleItem):
                params = list(inspect.signature(run.function()).parameters)
                assert params[0] == "scene" and params[2] == "quick", run.target
    experiments = next(i for i in ITEMS if i.name == "experiments")
    with pytest.raises(ForcecalError, match="'experiments' is an item of make bench-full only"):
        item_run(experiments, full=False)
    assert item_run(experiments, full=True) == experiments.full


def test_an_items_rows_of_a_shared_list_replace_only_its_own():
    """``skip`` holds the particle engine's rows (not labelled) and the experiments item's
    (labelled): a rerun of either replaces its own rows and keeps the other's."""
    from pipelines.bench.driver import ITEMS, merge_keys

    items = {i.name: i for i in ITEMS}
    bench = {"skip": [{"scene": "elastic"}, {"scene": "reference", "study": "experiments"}]}
    merge_keys(bench, {"skip": [{"scene": "free"}], "haptic": {"a": 1}},
               items["particle engine"])
    assert bench == {"skip": [{"scene": "reference", "study": "experiments"},
                              {"scene": "free"}], "haptic": {"a": 1}}
    merge_keys(bench, {"skip": [{"scene": "calibration"}], "experiments": [1]},
               items["experiments"])
    assert bench["skip"] == [{"scene": "free"},
                             {"scene": "calibration", "study": "experiments"}]
    assert bench["experiments"] == [1]


# the committed bench.json's keys by the item that writes them (a stand-in run returns them)
ITEM_KEYS = {"default pipeline run": ("calibration",), "run time vs error": ("pareto",),
             "reference timings": ("reference",),
             "particle engine": ("kernel", "gravity_dynamic", "skip", "haptic", "evaluators"),
             "stability limits": ("stability",), "experiments": ("skip", "experiments"),
             "haptic scale": ("haptic_scale",), "fe_convergence": ("fe_convergence",),
             "scale": ("scale", "scale_study"), "calibration methods": ("calibration_methods",),
             "volume term": ("volume_haptic",),
             "discretisation floor": ("discretisation_floor",),
             # not in the committed bench.json until a full bench has run it
             "scale reference": ()}


def _stand_in_items(monkeypatch, calls, reusing=()):
    """The bench's items with runs that return the committed bench.json's keys (each its own,
    :data:`ITEM_KEYS`) and record (name, selection) in ``calls``; the items named in
    ``reusing`` log a cache hit."""
    import logging

    from pipelines.bench import driver

    committed = json.loads((ROOT / "runs" / "bench" / "bench.json").read_text())

    def stand_in(name, selection):
        def run(bench_run):
            calls.append((name, selection))
            if name in reusing:
                logging.getLogger("pipelines.bench").warning("bench: reusing %s", name)
            keys = {k: committed[k] for k in ITEM_KEYS[name]}
            if "skip" in keys:
                own = (lambda r: "study" not in r) if name == "particle engine" else (
                    lambda r: r.get("study") == name)
                keys["skip"] = [{k: v for k, v in r.items() if k != "study"}
                                for r in keys["skip"] if own(r)]
            if name == "reference timings" and selection == "headline":
                keys["reference"] = {**keys["reference"], "wall_s_1rank": None}
            return keys
        return run

    monkeypatch.setattr(driver, "ITEMS", tuple(
        driver.Item(i.name, stand_in(i.name, "full"),
                    stand_in(i.name, "headline") if i.headline else None, i.needs_default,
                    i.labels_rows) for i in driver.ITEMS))


def test_a_headline_run_runs_its_items_in_order_and_records_their_cold_times(monkeypatch,
                                                                            tmp_path):
    """With every item's run stood in for: ``make bench`` runs the headline items (their
    headline versions) in the bench's order and sums their cold times into ``wall_s_cold``;
    an item that reuses earlier work keeps the earlier run's cold time; ``--only`` runs the
    item and the default run it needs, keeping the others' keys and cold times."""
    from pipelines.bench.driver import items_of, run_bench

    calls = []
    _stand_in_items(monkeypatch, calls)
    out = tmp_path / "bench-headline"
    first = run_bench(out, progress=False)
    headline = [i.name for i in items_of(False)]
    assert calls == [(name, "headline") for name in headline]
    assert first["selection"] == "headline" and first["reference"]["wall_s_1rank"] is None
    assert list(first["item_s"]) == headline and first["item_s_cold"] == first["item_s"]
    assert first["wall_s_cold"] == pytest.approx(sum(first["item_s"].values()))
    assert "experiments" not in first and "calibration_methods" not in first
    assert [r["scene"] for r in first["skip"]] == ["viscoelastic", "elastic", "free"]
    assert "Produced by `make bench`" in (out / "BENCH.md").read_text()
    assert json.loads((out / "bench.json").read_text()) == json.loads(json.dumps(first))

    calls.clear()
    _stand_in_items(monkeypatch, calls, reusing=("scale",))
    second = run_bench(out, progress=False)
    assert second["item_s_cold"]["scale"] == first["item_s_cold"]["scale"]
    assert second["item_s_cold"]["volume term"] == second["item_s"]["volume term"]

    calls.clear()
    third = run_bench(out, progress=False, only=("particle engine",))
    assert calls == [("default pipeline run", "headline"), ("particle engine", "headline")]
    assert third["wall_s"] == second["wall_s"]
    assert third["item_s_cold"]["scale"] == first["item_s_cold"]["scale"]
    assert third["reruns"][-1]["items"] == ["default pipeline run", "particle engine"]


def test_a_full_run_runs_every_item(monkeypatch, tmp_path):
    from pipelines.bench.driver import ITEMS, read_bench, run_bench

    calls = []
    _stand_in_items(monkeypatch, calls)
    bench = run_bench(tmp_path / "bench", full=True, progress=False)
    assert calls == [(i.name, "full") for i in ITEMS]
    assert bench["selection"] == "full" and bench["reference"]["wall_s_1rank"] is not None
    assert [r.get("study") for r in bench["skip"]] == [None] * 3 + ["experiments"] * 4
    read_bench(tmp_path / "bench" / "bench.json")
    assert "Produced by `make bench-full`" in (tmp_path / "bench" / "BENCH.md").read_text()


def test_the_headline_pareto_runs_the_first_settings_of_each_axis():
    from pipelines.bench.configs import HEADLINE_SETTINGS, configs

    scene = load_scene(SCENES / "tiny.toml")
    full, headline = configs(scene, True, full=True), configs(scene, True, full=False)

    def by_axis(rows):
        out = {}
        for c in rows:
            out.setdefault(c.axis, []).append(c.label)
        return out

    full, headline = by_axis(full), by_axis(headline)
    assert set(full) == set(headline) == {"mesh", "calibration points", "Nelder-Mead budget",
                                          "local tuning"}
    for axis, labels in headline.items():
        assert labels == full[axis][:HEADLINE_SETTINGS.get(axis, len(full[axis]))], axis
    assert len(headline["mesh"]) == 2 and len(full["mesh"]) == 3  # the coarse and the default


def test_the_headline_scale_study_keeps_a_wide_range_of_sizes_without_the_rank_timing(
        monkeypatch, tmp_path):
    from pipelines.bench import scale

    calls = []

    def child(args, cwd, mpi_ranks=0):
        calls.append((float(args[args.index("--length") + 1]), mpi_ranks))
        n = int(1e-3 / calls[-1][0] ** 3)  # vertices ~ length^-3
        return ({"ranks": mpi_ranks, "wall_s": 1.0} if mpi_ranks else
                {"vertices": n, "step_us": 0.1 * n, "calibration_s": 1e-4 * n ** 1.5})

    monkeypatch.setattr(scale, "_child", child)
    scene = load_scene(SCENES / "liver.toml")
    headline = scale.headline_study(scene, tmp_path, False)
    assert calls == [(length, 0) for length in scale.HEADLINE_LENGTHS[False]]
    assert headline["scale_study"]["ranks"]["runs"] == []
    assert headline["scale_study"]["exponents"]["calibration_s"] == pytest.approx(1.5, abs=0.02)
    calls.clear()
    scale.study(scene, tmp_path, False)
    assert [c for c, _ in calls] == list(scale.LENGTHS[False]) + [scale.LENGTHS[False][1]] * 2
    assert [r for _, r in calls][-2:] == [1, 2]
    vertices = sorted(int(1e-3 / length ** 3) for length in scale.HEADLINE_LENGTHS[False])
    assert vertices[-1] / vertices[0] > 5  # exponents over at least a 5x range of sizes


def test_the_headline_haptic_scale_leaves_out_the_largest_mesh_and_times_fewer_calls(
        monkeypatch):
    """The 12k-connector liver (the goal's mesh) stays; the 54k one is the full bench's, which
    times the goals' 10,000 calls per variant."""
    from tests.particle_models import box_model
    from pipelines.bench import haptic

    lengths, calls = [], []

    def mesh_model(scene, length):
        lengths.append(length)
        return box_model((2, 2, 2), K0=100.0), None, None

    def rows(*args, **kwargs):
        calls.append(kwargs["calls"])
        return []

    monkeypatch.setattr(haptic, "_mesh_model", mesh_model)
    monkeypatch.setattr(haptic, "tracked_node_by_rule", lambda mesh, fixed, rule: 0)
    monkeypatch.setattr(haptic, "mesh_rows", rows)
    monkeypatch.setattr(haptic, "volume_rows", rows)
    scene = load_scene(SCENES / "liver.toml")
    assert haptic.headline_study(scene, None, False)["haptic_scale"]["calls"] == 2000
    assert lengths == [None, 0.008]  # the scene's own mesh, then the 12k liver
    assert set(calls) == {haptic.HEADLINE_CALLS} and len(calls) == 6
    lengths.clear()
    calls.clear()
    assert haptic.study(scene, None, False)["haptic_scale"]["calls"] == 10_000
    assert lengths == [length for _, length in haptic.MESHES[False]] == [None, 0.008, 0.0045]
    assert set(calls) == {haptic.GOAL_CALLS} and len(calls) == 9


def test_the_headline_fe_convergence_leaves_out_the_finest_sag_level(monkeypatch, tmp_path):
    from pipelines.bench import fe_convergence

    seen = []
    monkeypatch.setattr(fe_convergence, "convergence",
                        lambda scene, levels, **kw: seen.append((levels, kw["sag_levels"])))
    monkeypatch.setattr(fe_convergence, "load_scene", lambda path: None)
    fe_convergence.headline_study(None, tmp_path, False)
    fe_convergence.study(None, tmp_path, False)
    assert seen == [(fe_convergence.LEVELS, fe_convergence.HEADLINE_SAG_LEVELS),
                    (fe_convergence.LEVELS, fe_convergence.SAG_LEVELS)]
    assert fe_convergence.HEADLINE_SAG_LEVELS == fe_convergence.SAG_LEVELS[:-1]


def test_an_only_run_of_a_full_item_or_into_another_selection_is_refused(tmp_path):
    from forcecal.errors import ForcecalError
    from pipelines.bench.driver import default_out, run_bench

    out = tmp_path / "bench"
    with pytest.raises(ForcecalError, match=r"\['experiments'\] run in make bench-full only"):
        run_bench(out, only=("experiments",))
    out.mkdir()
    shutil.copy(ROOT / "runs" / "bench" / "bench.json", out / "bench.json")  # a full run
    with pytest.raises(ForcecalError, match="is a full run, this one a headline run: pass --full"):
        run_bench(out, only=("stability limits",))
    assert sorted(p.name for p in out.iterdir()) == ["bench.json"]  # nothing ran
    assert default_out(False, False).as_posix() == "runs/bench-headline"
    assert default_out(True, False).as_posix() == "runs/bench"


def test_a_headline_bench_may_leave_the_1rank_reference_untimed(tmp_path):
    """The headline times the reference on 2 ranks only: its bench.json and BENCH.md say so;
    a full run must have both."""
    from forcecal.errors import DataFileError
    from pipelines.bench.driver import check_bench, read_bench
    from pipelines.bench.report import write_markdown

    bench = read_bench(ROOT / "runs" / "bench" / "bench.json")
    bench["reference"]["wall_s_1rank"] = None
    bench["reference"]["runs"].pop("1")
    with pytest.raises(DataFileError, match="reference.wall_s_1rank = None"):
        check_bench(bench)
    bench["selection"] = "headline"
    check_bench(bench)
    write_markdown(tmp_path / "BENCH.md", bench)
    text = (tmp_path / "BENCH.md").read_text()
    assert "Produced by `make bench` (`python -m pipelines bench`: the headline items" in text
    assert "not timed on 1 rank (`make bench-full` does)" in text


def test_the_make_targets_run_the_bench_command_with_their_selection(monkeypatch):
    """``make bench`` runs the headline into runs/bench-headline, ``make bench-full`` every
    item into runs/bench (the committed folder), ``make bench-quick`` the headline on the
    tiny scene: each target's command line, parsed by the ``bench`` command."""
    import re
    import shlex
    from pathlib import Path

    from pipelines import cli
    from pipelines.bench import driver

    recipes = dict(re.findall(r"^(bench[\w-]*): setup\n\t\$\(PY\) -m pipelines (.+)$",
                              (ROOT / "Makefile").read_text(), re.M))
    assert set(recipes) == {"bench", "bench-full", "bench-quick"}
    calls = []
    monkeypatch.setattr(driver, "run_bench", lambda out, **kw: calls.append((out, kw)))
    for target in ("bench", "bench-full", "bench-quick"):
        assert cli.main(shlex.split(recipes[target])) == 0
    assert [(out, kw["full"], kw["quick"], kw["only"], kw["cold"]) for out, kw in calls] == [
        (Path("runs/bench-headline"), False, False, (), False),
        (Path("runs/bench"), True, False, (), False),
        (Path("runs/bench-quick"), False, True, (), False)]
    calls.clear()
    assert cli.main(["bench", "--cold", "--only", " scale,volume term "]) == 0
    assert calls[0][0] == driver.default_out(False, False)
    assert calls[0][1]["only"] == ("scale", "volume term") and calls[0][1]["cold"]
