"""What is done about FE test points that fail (replaced under a rule, dropped from an explicit
list), the quarter that stops the run, and the message saying what failures share. Pure
numpy: the FE side is in tests/test_fe_point_failures.py."""

import dataclasses

import numpy as np
import pytest

from forcecal.errors import DataFileError
from forcecal.fe_failures import (FEFailures, PointFailure, apply_fe_failures,
                                  common_features, replay, too_many_failures)
from forcecal.point_selection import select_calibration_points, select_held_out_points
from forcecal.preflight import tet_quality
from forcecal.problem import build_problem, replacement_point
from forcecal.scene import load_scene, replace

from tests.conftest import SCENES


@pytest.fixture(scope="module")
def tiny():
    scene = load_scene(SCENES / "tiny.toml")
    return scene, build_problem(scene)


def _replacement(scene):
    return lambda problem, index, tried: replacement_point(scene, problem, index, tried)


def test_the_replacement_is_the_next_point_the_selection_rule_would_pick(tiny):
    """Held-out points: farthest-point sampling from the calibration points; the next
    candidate after the 8 is the 9th point of the same rule. Calibration points by 'auto'
    on a mesh whose cover exceeds n: the same, along the surface from the clamp."""
    scene, problem = tiny
    mesh, fixed = problem.mesh, problem.fixed
    nine = select_held_out_points(mesh, fixed, problem.calibration, 9)
    ninth = np.setdiff1d(nine, problem.held_out)
    assert len(ninth) == 1
    slot = len(problem.calibration) + 3
    assert replacement_point(scene, problem, slot, set()) == ninth[0]

    auto = replace(scene, test_points={"calibration": "auto", "n_calibration": 4})
    four = select_calibration_points(mesh, fixed, 4, "auto")
    five = select_calibration_points(mesh, fixed, 5, "auto")
    assert len(np.setdiff1d(five, four)) == 1  # the cover does not fit: sampling
    problem4 = dataclasses.replace(problem, calibration=four,
                                   held_out=select_held_out_points(mesh, fixed, four, 8))
    assert replacement_point(auto, problem4, 1, set()) == np.setdiff1d(five, four)[0]
    # never a current test point, nor one already tried
    tried = {int(np.setdiff1d(five, four)[0])}
    again = replacement_point(auto, problem4, 1, tried)
    assert again not in tried and again not in problem4.test_points


def test_failed_points_are_replaced_under_a_rule_and_dropped_from_a_list(tiny):
    scene, problem = tiny
    cal, held = problem.calibration, problem.held_out
    fails = [PointFailure(2, int(cal[2]), "relaxation", "diverged", {"time_s": 0.2}),
             PointFailure(9 + 1, int(held[1]), "indentation", "diverged", {"depth_m": 0.004})]
    current, records, applied = replay(problem, fails, _replacement(scene))
    assert [r["slot"] for r in records.replaced] == [2, 10] and not records.dropped
    assert records.replaced[0]["point"] == cal[2] and records.replaced[0]["role"] == "calibration"
    assert records.replaced[1]["role"] == "held_out"
    assert records.replaced[0]["reached"] == {"time_s": 0.2}
    assert current.test_points[2] == records.replaced[0]["by"]
    assert len(current.test_points) == len(problem.test_points) and len(applied) == 2
    # the replacement fails too: replaced again, in the next pass
    by = records.replaced[0]["by"]
    current2, records2, _ = replay(problem, fails + [PointFailure(2, by, "indentation", "x")],
                                   _replacement(scene))
    assert [r["point"] for r in records2.replaced if r["slot"] == 2] == [cal[2], by]
    assert current2.test_points[2] not in (cal[2], by)
    # decided from the set of failures only: any order gives the same
    assert replay(problem, fails[::-1], _replacement(scene))[1] == records
    # explicit lists: dropped
    listed = replace(scene, test_points={"calibration": cal.tolist(),
                                         "held_out": held.tolist()})
    current, records, _ = replay(problem, fails, _replacement(listed))
    assert not records.replaced and [d["point"] for d in records.dropped] == [cal[2], held[1]]
    assert len(current.calibration) == len(cal) - 1 and len(current.held_out) == len(held) - 1
    # what the calibration stage checks a reference against: the scene's points + the record
    again = apply_fe_failures(problem, records)
    np.testing.assert_array_equal(again.test_points, current.test_points)


def test_fe_failures_round_trip_and_refuse_a_damaged_attribute():
    f = FEFailures(({"point": 3, "by": 7, "experiment": "relaxation", "reason": "r"},), (),
                   {"experiment": "gravity_static", "reason": "no equilibrium"})
    import json
    assert FEFailures.from_json(json.dumps(f.to_json()), "x") == f
    assert FEFailures.from_json(None, "x") == FEFailures() and not FEFailures().any
    with pytest.raises(DataFileError, match="fe_failures"):
        FEFailures.from_json('{"replaced": [{"by": 3}]}', "x")
    problem = build_problem(load_scene(SCENES / "tiny.toml"))
    with pytest.raises(DataFileError, match="vertex 100000, which is not a test point"):
        apply_fe_failures(problem, FEFailures(({"point": 100000, "by": 1},)))


def test_more_than_a_quarter_stops_with_what_the_failures_share(tiny):
    """17 points: 4 failures are within a quarter, 5 are not. Failures at the 5 test points
    nearest the clamp are named as near it (the quarter of the free surface nearest the
    clamp holds at most 2 of the others)."""
    scene, problem = tiny
    mesh, fixed = problem.mesh, problem.fixed
    x = mesh.vertices

    def to_clamp(v):
        return np.min(np.linalg.norm(x[v][:, None] - x[fixed][None], axis=2), axis=1)

    order = np.argsort(to_clamp(problem.test_points))
    fails = [PointFailure(int(k), int(problem.test_points[k]), "relaxation", "diverging",
                          {"time_s": 0.2}) for k in order[:5]]
    assert too_many_failures(17, fails[:4], []) is None
    near = np.quantile(to_clamp(np.setdiff1d(mesh.surface_vertices, fixed)), 0.25)
    others = int(np.sum(to_clamp(problem.test_points[order[5:]]) <= near))
    assert np.all(to_clamp(problem.test_points[order[:5]]) <= near) and others <= 2
    features = common_features(mesh, fixed, problem.test_points, fails, tet_quality(mesh))
    message = str(too_many_failures(17, fails, features))
    assert message.startswith("5 FE test point runs failed, more than a quarter of the 17")
    assert "5 in relaxation" in message and "time reached 0.2-0.2 s" in message
    assert (f"5 of 5 near the clamp (within {near * 1e3:.3g} mm, as the nearest quarter of "
            f"the free surface; of the others: {others} of 12)") in message
    assert "first failure: vertex" in message and "diverging" in message


def test_the_crushed_tet_of_a_failed_gravity_test_is_named():
    """Two tets sharing a face; the apex of the second pushed through the shared face folds it
    (its corners enclose minus their volume at rest), the first stays whole."""
    from forcecal.fe_failures import CRUSHED_VOLUME_RATIO, crushed_tet
    from forcecal.mesh import TetMesh
    x = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, -1]], float) * 0.01
    mesh = TetMesh(x, np.array([[0, 1, 2, 3], [0, 2, 1, 4]]))
    assert np.all(mesh.signed_volumes > 0)
    quality = tet_quality(mesh)
    u = np.zeros_like(x)
    assert crushed_tet(mesh, u, np.array([0]), quality) is None  # at rest
    u[4, 2] = 0.02  # the apex from z = -1 to z = +1 cm: the mirror image of the tet
    said = crushed_tet(mesh, u, np.array([4]), quality)
    assert said == "tet 1 is folded (its corners enclose -1 x their volume at rest): it " \
                   "touches the clamp"
    # crushed to 0.1 of its volume, away from the clamp, a sliver in its rest shape
    u[4, 2] = 0.009
    assert crushed_tet(mesh, u, np.array([3]), quality) == (
        "tet 1 is crushed (its corners enclose 0.1 x their volume at rest)")
    assert crushed_tet(mesh, u, np.array([3]), np.array([0.9, 0.05])) == (
        "tet 1 is crushed (its corners enclose 0.1 x their volume at rest): it is poorly "
        "shaped (quality 0.05, below 0.1: remesh)")
    u[4, 2] = 0.0079  # 0.21 of its volume: compressed, not crushed
    assert CRUSHED_VOLUME_RATIO < 0.21
    assert crushed_tet(mesh, u, np.array([3]), quality) is None


def test_footprints_beyond_the_punch_reach_are_named_with_the_radius_that_keeps_them():
    """Failed points at the slab's top edge (tests/test_punch.py): their 21 mm footprints hold
    nodes 14.1 mm off the punch's face, beyond a 2 mm depth; radii from 5 mm (3 particles) to
    below 14.1 mm keep them within reach, 10 mm the shortest to write. On 20 mm cells no
    radius holding 3 particles does; a point on the top face (nothing beyond) among three
    failed at the edge leaves the 3/4 rule met, two of four not."""
    from forcecal.fe_failures import punch_reach
    from forcecal.indenter import punch_footprint
    from forcecal.mesh import box_mesh
    mesh = box_mesh((16, 4, 2), (0.08, 0.08, 0.04))
    x = mesh.vertices

    def at(*point):
        return int(np.argmin(np.linalg.norm(x - point, axis=1)))
    edge = [at(0.03, 0.0, 0.04), at(0.04, 0.0, 0.04), at(0.05, 0.0, 0.04)]
    face = [at(0.04, 0.04, 0.04), at(0.03, 0.04, 0.04)]

    def failed(vertices, depth=0.002):
        return {v: (n, depth) for v, n in zip(vertices, mesh.inward_normals(np.array(vertices)))}
    footprints = {v: punch_footprint(mesh, v, n, 0.021)
                  for v, (n, _) in failed(edge + face).items()}
    said = punch_reach(mesh, failed(edge), footprints, 0.021)
    assert said == ("the punch footprints of 3 of the 3 failed points hold particles beyond the "
                    "punch's reach, up to 14.1 mm from its face against the 2 mm depth (a flat "
                    "punch never touches them, its footprint holds them as if glued): "
                    "indentation.radius = 0.01 m keeps them within reach")
    assert punch_reach(mesh, failed(edge + face[:1]), footprints, 0.021).startswith(
        "the punch footprints of 3 of the 4 failed points")
    assert punch_reach(mesh, failed(edge[:2] + face), footprints, 0.021) is None
    assert punch_reach(mesh, failed(edge, 0.015), footprints, 0.021) is None
    # 20 mm cells along the edge too (tests/test_study_punch_reach.py): every footprint of 3
    # particles or more at the edge's middle vertex holds one across the edge
    coarse = box_mesh((4, 4, 2), (0.08, 0.08, 0.02))
    v = int(np.argmin(np.linalg.norm(coarse.vertices - [0.04, 0.0, 0.02], axis=1)))
    n = coarse.inward_normals(np.array([v]))[0]
    said = punch_reach(coarse, {v: (n, 0.002)}, {v: punch_footprint(coarse, v, n, 0.021)},
                       0.021)
    assert said.endswith(f"as if glued): no radius holding enough particles keeps vertex {v}'s "
                         f"within reach (test points where the surface is flat within the "
                         f"depth)")


def test_a_radius_is_written_as_short_as_its_range_allows_and_as_large():
    from forcecal.fe_failures import _round_within
    assert _round_within(0.005, 0.0141) == "0.01"
    assert _round_within(0.00604, 0.00877) == "0.008"  # not 0.007: nearer the scene's radius
    assert _round_within(0.0081, 0.0093) == "0.009"
    assert _round_within(0.00812, 0.00815) == "0.00814"
    assert _round_within(0.01, 0.0100001) == "0.01"  # the smallest radius itself works
    assert _round_within(0.009, 0.01) == "0.009"  # the range's end does not


def test_a_gravity_failure_the_preflight_expected_says_so():
    from forcecal.fe_failures import with_preflight
    record = {"experiment": "gravity_static", "reason": "gravity static: diverged",
              "reached": {"load_factor": 0.0039}}
    holding = {"support": {"holds": True, "linear_sag_m": 0.001, "body_size_m": 0.2}}
    falling = {"support": {"holds": False, "linear_sag_m": 0.464, "body_size_m": 0.229}}
    assert with_preflight(record, holding) == record
    assert with_preflight(None, falling) is None
    assert with_preflight(record, falling) == {**record, "reason": (
        "gravity static: diverged; expected by the mesh preflight: the support does not hold "
        "the body under its weight (linear sag under full gravity 464 mm, 2 x the body's size "
        "229 mm)")}
