"""The contact-size study (studies/indenter_radius.py): its common points, its table and its
command line."""
import json

import numpy as np
import pytest

from forcecal.indenter import mean_surface_edge, punch_footprint
from forcecal.point_selection import free_surface_vertices
from forcecal.problem import build_problem
from forcecal.scene import MIN_HELD_OUT, load_scene
from studies.indenter_radius import RADII_EDGES, common_points, main, markdown
from tests.conftest import ROOT, SCENES


def test_indenter_radius_study_points_are_valid_at_every_radius():
    """The contact-size study compares every radius on the same points: the scene's own where
    their footprints are valid at 1, 1.5 and 2 edge lengths, topped up to 8 held-out points by
    free surface vertices (never a calibration point)."""
    problem = build_problem(load_scene(SCENES / "liver_punch.toml"))
    h = mean_surface_edge(problem.mesh)
    assert h == pytest.approx(0.0161, rel=0.01)  # the punch scene's mean surface edge length (docs/punch.md)
    radii = [e * h for e in RADII_EDGES if e > 0]
    calibration, held_out = common_points(problem, radii)
    assert set(calibration) <= set(problem.calibration.tolist()) and len(calibration) >= 3
    assert len(held_out) == MIN_HELD_OUT and not set(held_out) & set(calibration)
    assert set(held_out) <= set(free_surface_vertices(problem.mesh, problem.fixed).tolist())
    for vertex in calibration + held_out:
        normal = problem.mesh.inward_normals(np.array([vertex]))[0]
        for radius in radii:
            assert len(punch_footprint(problem.mesh, vertex, normal, radius,
                                       fixed=problem.fixed)) >= 3


def test_the_table_of_the_committed_result_has_each_fit_at_each_size():
    """Rows: the size fitted at; columns: the size used at; the diagonal bold with the
    calibration error after it, a missing cross term 'failed'."""
    result = json.loads((ROOT / "runs" / "studies" / "indenter_radius.json").read_text())
    lines = markdown(result)
    assert lines[0] == "| fitted at \\ used at | vertex | 1 h | 1.5 h | 2 h |"
    vertex = next(r for r in result["rows"] if r["fitted_radius_edges"] == 0
                  and r["radius_edges"] == 0)
    assert lines[2].startswith(f"| vertex | **{100 * vertex['held_out_error']:.1f} %** / "
                               f"{100 * vertex['calibration_error']:.1f} % |")
    result["rows"] = [r for r in result["rows"] if r["fitted_radius_edges"] != 2
                      or r["radius_edges"] != 0]
    assert markdown(result)[5].startswith("| 2 h | failed |")


def test_the_command_line_names_its_scene_work_folder_and_output(monkeypatch, tmp_path):
    """``python -m studies.indenter_radius``: runs/studies/ by default; a scene without a
    punch (the tiny liver) is given one before the study runs."""
    import studies.indenter_radius as study

    seen = {}

    def fake(base, work):
        seen.update(indenter=base.indentation.indenter, work=work)
        return {"rows": [{"radius_edges": 0.0, "fitted_radius_edges": 0.0,
                          "held_out_error": 0.05, "calibration_error": 0.01}]}

    monkeypatch.setattr(study, "study", fake)
    out = tmp_path / "radius.json"
    main(["--scene", str(SCENES / "tiny.toml"), "--work", str(tmp_path / "w"),
          "--out", str(out)])
    assert seen == {"indenter": "punch", "work": tmp_path / "w"}
    assert json.loads(out.read_text())["rows"][0]["held_out_error"] == 0.05
    assert study.WORK.as_posix() == "runs/studies/indenter_radius"
    assert study.OUT.as_posix() == "runs/studies/indenter_radius.json"
