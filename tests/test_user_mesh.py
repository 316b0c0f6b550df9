"""End to end on a mesh read from a file (not generated), with the test points chosen by 'auto'.

The mesh is the user-organ bean of ``scenes/meshes/make_user_organ.py`` at a
coarse size (136 vertices), written to a ``.vtu`` in millimetres with y up as a
user's export would be; the scene is the tiny scene's fast settings with only
the mesh, the fixed-node rule, gravity and the test points changed.
"""
import importlib.util
import json
import math

import meshio
import numpy as np
import pytest

from forcecal.h5io import read_reference
from forcecal.mesh import coverage, read_mesh
from forcecal.scene import load_scene
from pipelines.report import ERROR_KEYS, TIMING_KEYS
from pipelines.stages import ORDER, run_pipeline
from tests.conftest import SCENES
from tests.test_pipeline_e2e import write_scene

pytestmark = [pytest.mark.slow, pytest.mark.fe, pytest.mark.mpi]

COARSE_MM = 25.0  # 136 vertices, 359 tets: seconds per FE curve


def user_organ_module():
    spec = importlib.util.spec_from_file_location("make_user_organ",
                                                  SCENES / "meshes" / "make_user_organ.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def user_run(tmp_path_factory):
    base = tmp_path_factory.mktemp("user_mesh")
    meshio.write(base / "organ.vtu", user_organ_module().make(COARSE_MM))
    scene_path = base / "organ.toml"
    write_scene(scene_path, {
        "mesh": {"source": "organ.vtu", "scale": 0.001},
        "fixed": {"axis": "y", "side": "max"},
        "gravity": {"acceleration": [0.0, -9.81, 0.0]},
        "test_points": {"calibration": "auto", "n_calibration": 6, "held_out": "auto",
                        "n_held_out": 8}})
    out = base / "out"
    outcomes = run_pipeline(load_scene(scene_path), out, progress=False, ranks=2)
    return base, out, outcomes


def test_a_mesh_from_a_file_runs_end_to_end_with_auto_test_points(user_run):
    base, out, outcomes = user_run
    assert [o.stage for o in outcomes if o.ran] == list(ORDER)
    mesh = read_mesh(base / "organ.vtu", scale=0.001)
    report = json.loads((out / "report.json").read_text())
    assert report["mesh"] == {"nodes": mesh.n_vertices, "tets": mesh.n_tets,
                              "connectors": len(mesh.edges)}
    for group, keys in (("errors", ERROR_KEYS), ("baseline_errors", ERROR_KEYS),
                        ("timings_s", TIMING_KEYS)):
        for k in keys:
            assert isinstance(report[group][k], float) and math.isfinite(report[group][k]), k
    # the reference holds the points 'auto' chose, and the report their coverage
    problem = read_reference(out / "reference.h5").problem
    tp = report["test_points"]
    assert tp["calibration"] == problem.calibration.tolist() and len(tp["calibration"]) == 6
    assert tp["held_out"] == problem.held_out.tolist() and len(tp["held_out"]) == 8
    assert tp["coverage"]["calibration"] == pytest.approx(
        coverage(mesh, problem.fixed, problem.calibration), abs=0)
    assert 0 < tp["coverage"]["calibration"] < 1  # 6 points cannot cover 102 vertices
    # hung from its top: every fixed vertex is on the top face, and the organ sags along -y
    np.testing.assert_allclose(mesh.vertices[problem.fixed, 1], mesh.vertices[:, 1].max(),
                               atol=1e-3)
    assert report["gravity"]["fe_max_static_sag_m"] > 0
