"""The punch reach study (studies/punch_reach.py): footprint geometry and the reach-limited
what-if rule."""
import json
from pathlib import Path

import numpy as np
import pytest

from calibration.synthetic import box_scene
from forcecal import indenter
from forcecal.problem import build_problem
from forcecal.scene import load_scene
from studies.punch_reach import deepest, footprint_geometry, summary, within_reach

ROOT = Path(__file__).resolve().parents[1]
RESULT = ROOT / "runs" / "studies" / "punch_reach.json"


def test_a_punch_holds_only_what_its_face_reaches_on_a_face_not_at_an_edge(tmp_path):
    """On the box's top face (20 mm cells) a punch of 21 mm holds the centre and its 4
    neighbours, all in the plane of its face: none out of reach. At a vertex of the top
    face's edge the inward normal (area-weighted) leans atan(1/2) from the vertical, so the
    punch's face is tilted: its neighbours 20 mm along the top lie 20 mm x sin(atan(1/2)) =
    20/sqrt(5) mm off the face, beyond the 2 mm depth."""
    scene = box_scene(tmp_path, cells=(4, 4, 2), size=(0.08, 0.08, 0.02),
                      test_points={"calibration": [20, 26, 50, 56],  # top face, off the clamp
                                   "held_out": [23, 38, 41, 35, 53, 8, 32, 44]},
                      indentation={"indenter": "punch", "radius": 0.021, "depth": 0.002},
                      relaxation={"depth": 0.002})
    problem = build_problem(scene)
    rows = footprint_geometry(scene, problem)
    assert [r["vertex"] for r in rows] == problem.test_points.tolist()
    at_edge = np.abs(problem.normals[:, 2]) < 1.0 - 1e-9
    assert at_edge.sum() == 3
    for row, edge in zip(rows, at_edge):
        if edge:
            assert row["nodes"] == 7 and row["beyond"] == 4
            assert row["max_gap_m"] == pytest.approx(0.02 / np.sqrt(5.0), rel=1e-12)
        else:
            assert row["nodes"] == 5 and row["beyond"] == 0 and row["max_gap_m"] < 1e-15
    s = summary(rows, deepest(scene))
    assert (s["points"], s["points_beyond"], s["nodes_beyond"]) == (12, 3, 12)
    assert s["max_gap_over_depth"] == pytest.approx(10.0 / np.sqrt(5.0), rel=1e-12)


@pytest.fixture(scope="module")
def liver_punch():
    scene = load_scene(ROOT / "scenes" / "liver_punch.toml")
    return scene, build_problem(scene)


def test_the_committed_result_is_what_the_liver_punch_scene_gives(liver_punch):
    """The committed geometry of the punch scene reproduces from the scene (same mesh, same
    rule): its summary and every point's row."""
    scene, problem = liver_punch
    committed = json.loads(RESULT.read_text())["scenes"]["scenes/liver_punch.toml"]
    rows = footprint_geometry(scene, problem)
    assert len(rows) == len(committed["points"])
    for row, kept in zip(rows, committed["points"]):
        assert row == pytest.approx(kept, rel=1e-9)
    assert summary(rows, deepest(scene)) == pytest.approx(committed["summary"], rel=1e-9)


def test_the_reach_rule_keeps_the_connected_nodes_within_the_depth(liver_punch):
    """Within :func:`within_reach`, the footprint of the point with the farthest node is the
    part of the rule's footprint within the depth of the face (connected to the point), and
    the rule is back after the context."""
    scene, problem = liver_punch
    depth = deepest(scene)
    rows = footprint_geometry(scene, problem)
    worst = int(np.argmax([r["max_gap_m"] for r in rows]))
    vertex, normal = problem.test_points[worst], problem.normals[worst]
    n = normal / np.linalg.norm(normal)
    radius = scene.indentation.radius

    def footprint():
        return indenter.punch_footprint(problem.mesh, vertex, normal, radius,
                                        fixed=problem.fixed)

    rule = footprint()
    with within_reach(depth):
        reach = footprint()
    assert np.array_equal(footprint(), rule)
    gap = np.abs((problem.mesh.vertices[reach] - problem.mesh.vertices[vertex]) @ n)
    assert vertex in reach and set(reach) < set(rule) and gap.max() <= depth
    assert len(reach) <= rows[worst]["nodes"] - rows[worst]["beyond"]
