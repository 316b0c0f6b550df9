"""Scene files: defaults, validation errors that name the key, documentation coverage."""
import dataclasses

import numpy as np

import pytest

from forcecal.errors import SceneError
from forcecal.scene import (SECTIONS, RelaxationSection, keys_table, load_scene, replace,
                            scene_from_dict)
from tests.conftest import ROOT, SCENES


def test_every_shipped_scene_loads():
    for path in SCENES.glob("*.toml"):
        scene = load_scene(path)
        assert scene.name


def test_liver_scene_material_is_consistent(liver_scene):
    m = liver_scene.material
    assert m.shear_modulus == pytest.approx(6000.0)
    assert m.long_term_factor == pytest.approx(0.4)
    # representative-value bounds from the issue: kappa 50-100 x mu, g in 0.2-0.5, tau1 < 1 s
    assert 50 <= m.kappa / m.shear_modulus <= 100
    assert all(0.2 <= g <= 0.5 for g in m.prony_g)
    assert m.prony_tau[0] < 1.0 and 10.0 <= m.prony_tau[1] <= 50.0


@pytest.mark.parametrize("doc, message", [
    ({"material": {"C10": "soft"}}, r"material.C10 = 'soft': expected number in Pa"),
    ({"material": {"stiffness": 1.0}}, r"unknown key\(s\) \['stiffness'\] in \[material\]"),
    ({"colour": "red"}, r"unknown top-level key"),
    ({"material": {"C10": -1.0}}, r"material.C10 = -1.0: must be > 0"),
    ({"material": {"prony_g": [0.6, 0.5]}}, r"must be < 1"),
    ({"material": {"prony_g": [0.3]}}, r"differ in length"),
    ({"relaxation": {"hold_time": 10.0}}, r"shorter than 5 x tau_max"),
    ({"fe": {"element": "Q2"}}, r"must be one of \['P1', 'P2', 'TH', 'ANP'\]"),
    ({"indentation": {"steps": 3}}, r"indentation.steps = 3: must be >= 10"),
    ({"particle": {"dt": "fast"}}, r"particle.dt must be 'auto'"),
    ({"gravity": {"acceleration": [0, -9.81]}}, r"gravity.acceleration .*expected list of 3"),
    ({"test_points": {"calibration": "some"}}, r"test_points.calibration must be 'auto'"),
    ({"name": "my scene"}, r"without slashes or spaces"),
    ({"gravity": {"record_interval": 0.001}},
     r"gravity.record_interval \(0.001 s\) is shorter than gravity.fe_dt \(0.005 s\)"),
    ({"test_points": {"n_held_out": 2}}, r"test_points.n_held_out = 2: must be >= 8"),
    # hold steps start at the ramp's 0.05 s: 30 of them overshoot a 0.5 s hold
    ({"material": {"prony_tau": [0.02, 0.1]}, "relaxation": {"hold_time": 0.5}},
     r"relaxation.hold_time = 0.5 s is shorter than relaxation.hold_steps x the ramp step "
     r"\(relaxation.ramp_time / relaxation.ramp_steps\) = 30 x 0.05 s = 1.5 s"),
])
def test_bad_scene_values_name_the_key(doc, message):
    with pytest.raises(SceneError, match=message):
        scene_from_dict(doc)


def test_bad_toml_and_missing_file(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("name = \n")
    with pytest.raises(SceneError, match="not valid TOML"):
        load_scene(bad)
    with pytest.raises(SceneError, match="does not exist"):
        load_scene(tmp_path / "nope.toml")


def test_replace_validates_and_fingerprints_change(liver_scene):
    th = replace(liver_scene, fe={"element": "TH"})
    assert th.fe.element == "TH"
    assert th.fingerprint("material") == liver_scene.fingerprint("material")
    assert th.fingerprint("fe") != liver_scene.fingerprint("fe")
    with pytest.raises(SceneError):
        replace(liver_scene, fe={"element": "Q1"})


def test_the_scenes_page_documents_every_scene_key():
    page = (ROOT / "docs" / "scenes.md").read_text()
    for sec, cls in SECTIONS.items():
        for f in dataclasses.fields(cls):
            assert f"`{sec}.{f.name}`" in page, f"docs/scenes.md lacks scene key {sec}.{f.name}"
    assert keys_table().splitlines()[0] in page


def test_relaxation_schedule_resolves_ramp_and_ends_on_time(liver_scene):
    from forcecal.schedules import indentation_depths, relaxation_schedule
    r = liver_scene.relaxation
    t, d = relaxation_schedule(r)
    assert len(t) == r.ramp_steps + r.hold_steps
    assert t[r.ramp_steps - 1] == pytest.approx(r.ramp_time)
    assert t[-1] == pytest.approx(r.ramp_time + r.hold_time, rel=1e-12)
    steps = np.diff(np.r_[0.0, t])
    assert np.all(steps > 0)
    # first hold step equals the ramp step, later ones grow
    assert steps[r.ramp_steps] == pytest.approx(r.ramp_time / r.ramp_steps)
    assert np.all(np.diff(steps[r.ramp_steps:]) > 0)
    assert d[-1] == r.depth and np.all(d[r.ramp_steps - 1:] == r.depth)
    np.testing.assert_allclose(indentation_depths(liver_scene.indentation)[[0, -1]],
                               [0.0005, 0.005])


def test_relaxation_schedule_refuses_hold_steps_that_cannot_fit():
    """Built directly (no scene validation), the schedule still refuses instead of returning
    times that do not increase (a FE march would silently skip a sample)."""
    from forcecal.schedules import relaxation_schedule
    with pytest.raises(SceneError, match="relaxation.hold_time = 0.5 s is shorter"):
        relaxation_schedule(RelaxationSection(hold_time=0.5))
    t, _ = relaxation_schedule(RelaxationSection(hold_time=1.5))  # exactly 30 ramp steps
    assert np.all(np.diff(t) > 0) and t[-1] == pytest.approx(2.0)


def test_indentation_depth_in_the_wrong_unit_is_refused(liver_scene, liver_problem):
    """5 meant as mm: refused against the mesh before any test point is chosen."""
    from forcecal.problem import build_problem
    mesh = liver_problem.mesh
    with pytest.raises(SceneError, match=r"indentation.depth = 5 m is not below 0.5 x the "
                       r"mesh's mean edge length \(0.5 x 0.0205 = 0.0102 m; .*in metres "
                       r"\(5 mm is 0.005\)"):
        build_problem(replace(liver_scene, indentation={"depth": 5.0}), mesh)
    with pytest.raises(SceneError, match=r"relaxation.depth = 0.02 m is not below"):
        build_problem(replace(liver_scene, relaxation={"depth": 0.02}), mesh)


def test_an_explicit_held_out_list_needs_8_points(liver_scene, liver_problem):
    from forcecal.problem import build_problem
    p = liver_problem
    points = {"calibration": p.calibration.tolist(), "held_out": p.held_out[:7].tolist()}
    with pytest.raises(SceneError, match="test_points.held_out lists 7 vertices; at least 8"):
        build_problem(replace(liver_scene, test_points=points), p.mesh)
    points["held_out"] = p.held_out.tolist()
    rebuilt = build_problem(replace(liver_scene, test_points=points), p.mesh)
    np.testing.assert_array_equal(rebuilt.held_out, p.held_out)
