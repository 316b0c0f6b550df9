"""Bad scene values refused at load or before any work, with a message naming the key
(tester's defects 2-6, 12, 13, 16, 17): fast, no FE."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from forcecal.cost import check_cost, check_generated_cost
from forcecal.errors import DataFileError, MeshError, SceneError
from forcecal.h5io import check_output_file, section_differences
from forcecal.liver_mesh import estimated_liver_vertices
from forcecal.problem import load_mesh
from forcecal.scene import (MaterialSection, load_scene, replace, scene_from_dict)
from tests.conftest import ROOT, SCENES

LIVER = SCENES / "liver.toml"
TINY = SCENES / "tiny.toml"


def test_every_shipped_scene_still_loads_and_is_priced():
    for path in sorted(SCENES.glob("*.toml")):
        scene = load_scene(path)
        if scene.mesh.source == "generate":
            check_generated_cost(scene)  # the pre-meshing estimate accepts every shipped scene


@pytest.mark.parametrize("doc, words", [
    ({"test_points": {"calibration": []}},
     ["test_points.calibration = []", "at least one calibration point"]),
    ({"particle": {"dt_safety": 1.5}}, ["particle.dt_safety = 1.5", "must be in (0, 1)"]),
    ({"particle": {"dt_safety": 1.0}}, ["particle.dt_safety = 1.0", "must be in (0, 1)"]),
    ({"gravity": {"acceleration": [0, 0, -981]}},
     ["gravity.acceleration", "981", "above 100 m/s^2", "cm/s^2", "-9.81"]),
    ({"mesh": {"characteristic_length": 40.0}},
     ["mesh.characteristic_length = 40", "not small against the generated liver",
      "0.065 m", "in mm?"]),
])
def test_bad_values_are_refused_at_load_naming_the_key(doc, words):
    with pytest.raises(SceneError) as info:
        scene_from_dict(doc)
    for word in words:
        assert word in str(info.value), (word, str(info.value))


def test_valid_neighbours_of_the_refused_values_load():
    scene_from_dict({"particle": {"dt_safety": 0.99}})
    scene_from_dict({"gravity": {"acceleration": [0, 0, -98.1]}})  # 10 g
    scene_from_dict({"test_points": {"calibration": [1, 2, 3]}})
    scene_from_dict({"test_points": {"calibration": [1], "held_out": list(range(2, 10))}})
    # more folds than calibration points: one fold per point (logged, tested below)
    scene_from_dict({"calibration": {"method": "gradient", "cv_folds": 50},
                     "test_points": {"n_calibration": 9}})
    scene_from_dict({"mesh": {"characteristic_length": 0.04}})
    scene_from_dict({"mesh": {"source": "organ.vtu", "characteristic_length": 40.0}})


def test_cost_counts_uniform_refinement_and_names_fe_refine():
    liver = load_scene(LIVER)
    check_cost(replace(liver, fe={"refine": 2}), 282, 1400)
    for level in (3, 6):
        with pytest.raises(SceneError) as info:
            check_cost(replace(liver, fe={"refine": level}), 282, 1400)
        text = str(info.value)
        assert f"fe.refine = {level}" in text and "lower fe.refine" in text, text
        assert "above the limit of 2e+08" in text
    # the steps stay the cause when they alone are too many
    with pytest.raises(SceneError, match=r"from indentation.steps = 10000000"):
        check_cost(replace(liver, indentation={"steps": 10_000_000}, fe={"refine": 1}),
                   282, 1400)


def test_cost_counts_punch_rim_refinement():
    punch = load_scene(SCENES / "liver_punch.toml")  # local_refine = 3
    check_cost(punch, 282, 1400)
    with pytest.raises(SceneError) as info:
        check_cost(replace(punch, fe={"local_refine": 12}), 282, 1400)
    assert "fe.local_refine = 12" in str(info.value) and "lower fe.local_refine" in str(
        info.value)


def test_generated_liver_is_priced_before_meshing(monkeypatch):
    import forcecal.problem as problem

    def no_gmsh(length):
        raise AssertionError("gmsh must not run")
    monkeypatch.setattr(problem, "generate_liver", no_gmsh)
    fine = replace(load_scene(TINY), mesh={"characteristic_length": 0.0005})
    assert estimated_liver_vertices(0.0005) > 1e6
    with pytest.raises(SceneError) as info:
        load_mesh(fine)
    text = str(info.value)
    assert "mesh.characteristic_length = 0.0005" in text
    assert "raise mesh.characteristic_length" in text and "estimated" in text


def test_vertex_estimate_is_close_to_gmsh():
    from forcecal.liver_mesh import generate_liver
    for length in (0.0182, 0.01):
        actual = generate_liver(length).n_vertices
        assert abs(estimated_liver_vertices(length) - actual) <= 0.1 * actual


def test_directories_are_named_as_directories(tmp_path):
    with pytest.raises(SceneError, match="is a directory, not a file"):
        load_scene(SCENES)
    scene = tmp_path / "s.toml"
    scene.write_text('[mesh]\nsource = ".."\n')
    with pytest.raises(MeshError, match="is a directory, not a file"):
        load_mesh(load_scene(scene))


def test_garbage_mesh_file_is_one_line_naming_file_and_format(tmp_path, capfd):
    (tmp_path / "g.vtu").write_text("garbage\n")
    scene = tmp_path / "s.toml"
    scene.write_text('[mesh]\nsource = "g.vtu"\n')
    with pytest.raises(MeshError) as info:
        load_mesh(load_scene(scene))
    text = str(info.value)
    assert "g.vtu" in text and "as vtu" in text and "SystemExit" not in text, text
    out, err = capfd.readouterr()
    assert "Error" not in out and "Error" not in err  # meshio's own line is captured


def test_output_file_path_is_checked(tmp_path):
    with pytest.raises(DataFileError, match="is a directory; give the path of the file"):
        check_output_file(tmp_path)
    (tmp_path / "afile").write_text("")
    with pytest.raises(DataFileError, match="is a file, not a directory"):
        check_output_file(tmp_path / "afile" / "reference.h5")
    assert check_output_file(tmp_path / "new" / "reference.h5").parent.is_dir()


@pytest.mark.parametrize("module", ["reference_fe", "calibration"])
def test_commands_refuse_a_directory_out_before_any_work(module, tmp_path):
    out = tmp_path / "outdir"
    out.mkdir()
    args = [sys.executable, "-m", module, "--scene", str(TINY), "--out", str(out)]
    if module == "calibration":
        args += ["--reference", str(tmp_path / "reference.h5")]
    run = subprocess.run(args, cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert run.returncode == 2, run.stderr
    assert run.stderr.strip().splitlines()[-1].startswith(f"error: --out {out} is a directory")
    assert not (tmp_path / "checkpoints").exists() and not list(out.iterdir())


def test_material_differences_name_the_keys():
    differ = section_differences("material", MaterialSection(C10=2500.0), MaterialSection(),
                                 ("reference",))
    assert differ == ["material.C10 = 2500.0 (scene: 2000.0)"]


def test_scene_keys_table_on_the_scenes_page_is_current():
    from forcecal.scene import keys_table
    assert keys_table() in (ROOT / "docs" / "scenes.md").read_text()


def test_more_folds_than_calibration_points_give_one_fold_per_point():
    from calibration.gradient_solver import folds_of
    assert len(folds_of(3, 5)) == 3 and len(folds_of(9, 5)) == 5



def test_the_fe_estimate_prices_the_opt_in_experiments():
    """``fe_work`` on the tiny scene (particle mesh 100 vertices, 500 edges, no refinement):
    the second support adds one gravity test's steps to the gravity keys, the whole-body data
    two static loads and two eigen-solves, and the floor, for each of its two elements on the
    particle mesh, the gravity tests and the held-out points' curves at 0.12 of a reference
    step; the core-seconds grow by the same factor (one rate)."""
    from forcecal.cost import FLOOR_SOLVE_FRACTION, fe_core_seconds, fe_work
    scene = load_scene(TINY)
    base_experiments = list(scene.experiments)
    g, r, n = scene.gravity, scene.relaxation, 100
    dynamic, static = round(g.duration / g.fe_dt), g.static_load_steps  # 60 and 4 steps
    curves = scene.indentation.steps + r.ramp_steps + r.hold_steps  # 22 steps per point
    held = scene.test_points.n_held_out

    def work(*added):
        return fe_work(replace(scene, experiments=base_experiments + list(added)), n, 500)

    base = work()
    assert base == {"indentation.steps": 17 * 10 * n, "relaxation.hold_steps": 17 * 12 * n,
                    "gravity.fe_dt": dynamic * n, "gravity.static_load_steps": static * n}
    second = work("second_support")
    assert second == {**base, "gravity.fe_dt": 2 * dynamic * n,
                      "gravity.static_load_steps": 2 * static * n}
    assert work("body") == {**base, "body.load_steps": (2 * scene.body.load_steps + 2) * n}
    floor = work("floor")
    assert floor == {**base, "experiments": pytest.approx(
        2 * FLOOR_SOLVE_FRACTION * (dynamic + static + held * curves) * n, rel=1e-12)}
    both = work("second_support", "floor")
    assert both["experiments"] == pytest.approx(
        2 * FLOOR_SOLVE_FRACTION * (2 * (dynamic + static) + held * curves) * n, rel=1e-12)
    total = sum(floor.values())
    assert fe_core_seconds(scene, total, n, 500) == pytest.approx(
        fe_core_seconds(scene, sum(base.values()), n, 500) * total / sum(base.values()),
        rel=1e-12)
