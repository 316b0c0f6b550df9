"""The second held-out body test's support (``[second_support]``): refused before any FE work
when it cannot make a second test -- too few vertices, the ``[fixed]`` set itself, a support
that does not hold the body (the preflight's linear check), a tracked vertex it clamps -- each
naming the ``second_support`` keys. The FE side is in tests/test_fe_second_support.py, the
particle side and the report in tests/test_validation_failures.py."""

import dataclasses

import numpy as np
import pytest

from calibration.synthetic import box_scene
from forcecal.errors import SceneError
from forcecal.preflight import SAG_LIMIT, check_support
from forcecal.problem import build_problem, check_second_support, second_support
from forcecal.scene import load_scene, replace
from pipelines.runners.common import Context
from pipelines.stages import STAGES

from tests.conftest import SCENES

ASKED = ["indentation", "relaxation", "gravity_static", "gravity_dynamic", "second_support"]


@pytest.fixture(scope="module")
def tiny():
    """The tiny liver asking for the second support (the section's default: its top)."""
    scene = replace(load_scene(SCENES / "tiny.toml"), experiments=ASKED)
    return scene, build_problem(scene)


def test_the_default_second_support_hangs_the_tiny_liver_from_its_top(tiny):
    scene, problem = tiny
    support = check_second_support(scene, problem)
    z = problem.mesh.vertices[:, 2]
    assert np.array_equal(support.fixed, np.nonzero(z >= z.max() - 0.01)[0])
    assert len(support.fixed) == 10 and not np.intersect1d(support.fixed, problem.fixed).size
    # its tracked vertex: the scene's rule applied to this clamp
    free = np.setdiff1d(np.arange(problem.mesh.n_vertices), support.fixed)
    centre = problem.mesh.vertices[support.fixed].mean(axis=0)
    far = free[np.argmax(np.linalg.norm(problem.mesh.vertices[free] - centre, axis=1))]
    assert support.tracked_node == far


@pytest.mark.parametrize("keys, message", [
    ({"tolerance": 0.001}, r"second_support rule \(z max \+- 0.001 m\) selects 1 vertices; at "
                           r"least 3 non-collinear ones are needed to hold the organ \(widen "
                           r"second_support.tolerance\)"),
    ({"axis": "z", "side": "min", "tolerance": 0.00099},  # [fixed]: 0.001, the same set
     r"second_support \(axis 'z', side 'min', tolerance 0.00099 m\) selects the same 17 "
     r"vertices as \[fixed\]"),
])
def test_a_support_that_is_no_second_one_is_refused_naming_its_keys(tiny, keys, message):
    scene, problem = tiny
    with pytest.raises(SceneError, match=message):
        second_support(replace(scene, second_support=keys), problem)


def test_a_support_that_does_not_hold_the_body_is_refused_before_any_fe_work(tiny, tmp_path):
    """Three vertices at the tip of a lobe: the linear sag under full gravity is 2.6 m, ten
    times the body's size (the preflight's check of the first support, its limit a quarter
    of the size); the pipeline's first stage refuses it while it prices the scene."""
    scene, problem = tiny
    tip = replace(scene, second_support={"axis": "x", "side": "min", "tolerance": 0.01})
    fixed = second_support(tip, problem).fixed
    linear = check_support(problem.mesh, fixed, scene.material, scene.gravity.acceleration)
    assert len(fixed) == 3 and linear.rigid_modes == 0
    assert linear.sag_m > 10 * SAG_LIMIT * linear.body_size_m
    words = (r"second_support \(axis 'x', side 'min', tolerance 0.01 m\) does not hold the body "
             rf"under its weight: the linear sag of its 3 clamped vertices is "
             rf"{linear.sag_m * 1e3:.4g} mm")
    with pytest.raises(SceneError, match=words):
        check_second_support(tip, problem)
    with pytest.raises(SceneError, match=words):
        STAGES["reference"].inputs(Context(tip, tmp_path, False, 1))
    # the scene without the experiment does not read the section
    STAGES["reference"].inputs(Context(replace(tip, experiments=ASKED[:4]), tmp_path, False, 1))


def test_a_tracked_vertex_the_second_support_clamps_is_refused(tmp_path):
    scene = box_scene(tmp_path, second_support={"axis": "z", "side": "max", "tolerance": 1e-4},
                      test_points={"n_calibration": 4})
    problem = build_problem(scene)
    top = int(np.argmax(problem.mesh.vertices[:, 2]))
    listed = dataclasses.replace(scene, gravity=dataclasses.replace(scene.gravity,
                                                                    tracked_node=top))
    with pytest.raises(SceneError, match=rf"gravity.tracked_node = {top} is clamped by "
                                         r"second_support \(axis 'z', side 'max'"):
        second_support(listed, problem)
