"""End to end on a mesh read from a file (not generated), with the test points chosen by 'auto'.

The file is written the way a user's export often comes: coordinates in
millimetres, y up (``mesh.scale = 0.001``, ``fixed.axis = "y"``, gravity along
-y). Its solid is the tiny scene's coarse liver (78 vertices, resting on its
flat base) rotated, so the physics is the tiny end-to-end test's and this test
is about the file, the axes and the 'auto' points. (A user's organ hung from its
top is ``scenes/user_organ.toml``: its gravity stage needs the calibrated springs kept
valid in tension, docs/calibration.md.)
"""
import json
import math

import meshio
import numpy as np
import pytest

from forcecal.h5io import read_reference
from forcecal.liver_mesh import generate_liver
from forcecal.mesh import read_mesh
from forcecal.point_selection import coverage
from forcecal.scene import load_scene
from pipelines.report import ERROR_KEYS, TIMING_KEYS
from pipelines.stages import ORDER, run_pipeline
from tests.test_pipeline_e2e import write_scene

pytestmark = [pytest.mark.slow, pytest.mark.fe, pytest.mark.mpi]

# (x, y, z) -> (x, z, -y): a proper rotation (tets keep their orientation) putting z up on y
Z_UP_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


@pytest.fixture(scope="module")
def user_run(tmp_path_factory):
    base = tmp_path_factory.mktemp("user_mesh")
    liver = generate_liver(0.04)
    meshio.write(base / "organ.vtu", meshio.Mesh(1000.0 * liver.vertices @ Z_UP_TO_Y_UP.T,
                                                 [("tetra", liver.tets)]))
    scene_path = base / "organ.toml"
    write_scene(scene_path, {
        "mesh": {"source": "organ.vtu", "scale": 0.001},
        "fixed": {"axis": "y", "side": "min"},
        "gravity": {"acceleration": [0.0, -9.81, 0.0]},
        "test_points": {"calibration": "auto", "n_calibration": 9, "held_out": "auto",
                        "n_held_out": 8}})
    out = base / "out"
    outcomes = run_pipeline(load_scene(scene_path), out, progress=False, ranks=2)
    return base, out, outcomes


def test_a_mesh_from_a_file_runs_end_to_end_with_auto_test_points(user_run):
    base, out, outcomes = user_run
    assert [o.stage for o in outcomes if o.ran] == list(ORDER)
    mesh = read_mesh(base / "organ.vtu", scale=0.001)
    report = json.loads((out / "report.json").read_text())
    assert report["mesh"] == {"nodes": 78, "tets": 186, "connectors": 336}
    for group, keys in (("errors", ERROR_KEYS), ("baseline_errors", ERROR_KEYS),
                        ("timings_s", TIMING_KEYS)):
        for k in keys:
            assert isinstance(report[group][k], float) and math.isfinite(report[group][k]), k
    # the reference holds the points 'auto' chose, and the report their coverage
    problem = read_reference(out / "reference.h5").problem
    tp = report["test_points"]
    assert tp["calibration"] == problem.calibration.tolist() and len(tp["calibration"]) == 9
    assert tp["held_out"] == problem.held_out.tolist() and len(tp["held_out"]) == 8
    assert tp["coverage"]["calibration"] == coverage(mesh, problem.fixed, problem.calibration)
    assert 0 < tp["coverage"]["calibration"] < 1  # a greedy cover needs 11 points, not 9
    # the base, now at the lowest y, is what is fixed
    np.testing.assert_allclose(mesh.vertices[problem.fixed, 1], mesh.vertices[:, 1].min(),
                               atol=1e-3)
    assert report["gravity"]["fe_max_static_sag_m"] > 0
