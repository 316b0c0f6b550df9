"""Pipeline parts: stage cache, particle gravity runs and gravity.h5, report errors, XDMF fields."""
import ast
import dataclasses
import os
import re
import subprocess
import sys
from typing import Callable

import h5py
import numpy as np
import pytest

from forcecal.errors import DataFileError, ParameterError
from forcecal.mesh import box_mesh
from forcecal.problem import Problem
from forcecal.scene import REFUSALS, scene_from_dict
from particle.model import build_model
from particle.params import ConnectorParams
from particle.stability import connector_strains
from forcecal.provenance import (FE, FE_BENCH, FIT, NOT_RESULT, STAGE_CODE, CodeDependencies,
                                 file_digest, import_closure, source_digest)
from pipelines.cache import Cache, StageInputs
from calibration.gravity_check import gravity_outcome
from pipelines.gravity import GravityRuns, GravityTest, read_gravity, write_gravity
from pipelines.report import (CURVE_KEYS, ERROR_KEYS, TIMING_KEYS, check_report,
                              gravity_dynamic_error, gravity_static_error)
from pipelines.stages import STAGES
from tests.conftest import ROOT


@pytest.fixture
def column():
    """A 1 x 1 x 4 cell box column, 10 mm cells, clamped at its base (z = 0)."""
    mesh = box_mesh((1, 1, 4), (0.01, 0.01, 0.04))
    fixed = np.nonzero(mesh.vertices[:, 2] == 0.0)[0]
    top = np.nonzero(np.isclose(mesh.vertices[:, 2], 0.04))[0]
    return Problem(mesh=mesh, fixed=fixed, calibration=top[:2], held_out=top[2:3],
                   tracked_node=int(top[-1]))


def linear_params(n: int, K0: float = 200.0) -> ConnectorParams:
    return ConnectorParams.uniform(n, K0=K0, k1=50.0, b1=5.0, k2=20.0, b2=40.0)


# ------------------------------------------------------------------------------- cache

def test_cache_reruns_on_each_kind_of_change(tmp_path):
    cache = Cache(tmp_path)
    (tmp_path / "out.h5").write_bytes(b"result")
    inputs = StageInputs(scene={"material": "m1", "fe": "f1"}, mesh="mesh1",
                         upstream={"reference.h5": "r1"}, code={"particle/model.py": "c1"})
    assert cache.check("stage", inputs) == ["no cache record"]
    cache.store("stage", inputs, ["out.h5"], 1.5)
    assert cache.check("stage", inputs) == []
    assert cache.elapsed("stage") == 1.5
    changed = StageInputs(scene={"material": "m2", "fe": "f1"}, mesh="mesh2",
                          upstream={"reference.h5": "r2"}, code={"particle/model.py": "c2"})
    assert cache.check("stage", changed) == ["scene [material] changed", "mesh changed",
                                             "reference.h5 changed",
                                             "code changed: particle/model.py"]
    (tmp_path / "out.h5").write_bytes(b"edited by hand")
    assert cache.check("stage", inputs) == ["output out.h5 was modified"]
    (tmp_path / "out.h5").unlink()
    assert cache.check("stage", inputs) == ["output out.h5 is missing"]


def test_unreadable_cache_record_means_rerun(tmp_path):
    cache = Cache(tmp_path)
    cache.record_path("stage").parent.mkdir()
    cache.record_path("stage").write_text("{ not json")
    assert cache.check("stage", StageInputs()) == ["no cache record"]


def test_import_closure_follows_the_imports_only(tmp_path, monkeypatch):
    pkg = tmp_path / "fc_demo_pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "entry.py").write_text("from fc_demo_pkg import used\n\ndef f():\n"
                                  "    import fc_demo_pkg.lazy\n")
    for name in ("used", "lazy", "unrelated"):
        (pkg / f"{name}.py").write_text("X = 1\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    assert set(import_closure(("fc_demo_pkg.entry",))) == {
        "fc_demo_pkg", "fc_demo_pkg.entry", "fc_demo_pkg.used", "fc_demo_pkg.lazy"}
    # a package entry stands for all of its modules
    assert "fc_demo_pkg.unrelated" in import_closure(("fc_demo_pkg",))
    with pytest.raises(DataFileError, match="fc_demo_pkg.missing"):
        import_closure(("fc_demo_pkg.missing",))
    with pytest.raises(DataFileError, match="not an importable package"):
        import_closure(("fc_no_such_package.mod",))


def test_code_digests_hold_the_declared_code_only(tmp_path, monkeypatch):
    pkg = tmp_path / "fc_decl_pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("VERSION = 1\n")
    (pkg / "entry.py").write_text("from fc_decl_pkg import used\n\ndef f():\n"
                                  "    import fc_decl_pkg.sub.lazy\n")
    (pkg / "sub" / "__init__.py").write_text('"""Docstring only."""\n')
    for name in ("used", "sub/lazy", "unrelated"):
        (pkg / f"{name}.py").write_text("X = 1\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    code = CodeDependencies(runs=("fc_decl_pkg.entry",),
                            reads=("fc_decl_pkg.entry", "fc_decl_pkg.used", "fc_decl_pkg.sub"))
    before = code.digests()
    assert set(before) == {"fc_decl_pkg/entry.py", "fc_decl_pkg/used.py",
                           "fc_decl_pkg/sub/__init__.py", "fc_decl_pkg/sub/lazy.py"}
    # the package's __init__ runs but is not declared: a dependency the key would miss
    assert code.undeclared() == ["fc_decl_pkg"]
    assert dataclasses.replace(code, reads=code.reads + ("fc_decl_pkg",)).undeclared() == []
    for edited in ("unrelated.py", "__init__.py"):  # outside the declared code
        (pkg / edited).write_text("X = 2\n")
        assert code.digests() == before
    # comments, layout and docstrings do not count; code does
    (pkg / "used.py").write_text('"""A module."""\n# why X is 1\nX  =  1\n')
    assert code.digests() == before
    for name in ("used", "sub/lazy"):
        (pkg / f"{name}.py").write_text("X = 3\n")
        after = code.digests()
        assert after[f"fc_decl_pkg/{name}.py"] != before[f"fc_decl_pkg/{name}.py"]
    assert StageInputs(code=after).changes_from({"code": before}) == [
        "code changed: fc_decl_pkg/sub/lazy.py, fc_decl_pkg/used.py"]
    # a module the entry starts importing, with code in it, is undeclared until declared
    (pkg / "sub" / "__init__.py").write_text("from fc_decl_pkg import unrelated\n")
    assert "fc_decl_pkg.unrelated" in code.undeclared()


def test_source_digest_leaves_out_the_ignored_definitions_only(tmp_path):
    module = tmp_path / "sections.py"
    source = ("class Read:\n    x: int = {}\n\n\nclass Unread:\n    y: int = {}\n\n\n"
              "def refuse(x):\n    if x > {}:\n        raise ValueError(x)\n")
    module.write_text(source.format(1, 1, 1))
    ignored = frozenset({"Unread", "refuse"})
    before, whole = source_digest(module, ignored), source_digest(module)
    module.write_text(source.format(1, 2, 1))  # a new default in an unread class
    assert source_digest(module, ignored) == before
    assert source_digest(module) != whole
    module.write_text(source.format(1, 2, 5))  # another refusal
    assert source_digest(module, ignored) == before
    module.write_text(source.format(2, 2, 5))  # a new default in a class that is read
    assert source_digest(module, ignored) != before


def test_every_cached_computation_declares_the_code_it_imports():
    # a module a computation imports at run time is in its key, or known not to change
    # its result (NOT_RESULT, each with its reason), or holds no code
    for code in (FE, FIT, FE_BENCH, *STAGE_CODE.values()):
        assert code.undeclared() == [], code.runs
    assert set(STAGE_CODE) == set(STAGES)
    assert all(STAGES[name].code is code for name, code in STAGE_CODE.items())
    for name, reason in NOT_RESULT.items():
        assert import_closure((name,)) and reason
    assert not any(n.startswith(("reference_fe", "particle", "calibration.core"))
                   for n in NOT_RESULT)


def test_the_fe_code_key_leaves_out_the_sections_the_fe_does_not_read():
    # a new [calibration] key must not make an FE reference stale; a new [fe] key must
    assert FE.ignored_definitions() == {"forcecal.scene": {
        "ParticleSection", "CalibrationSection", "OutputsSection", "VerdictSection",
        *REFUSALS}}
    assert STAGE_CODE["reference"].ignored_definitions() == FE.ignored_definitions()
    assert FIT.ignored_definitions() == {"forcecal.scene": set(REFUSALS)}
    # no module of the FE reads those sections' values (but forcecal.scene, which defines
    # and validates them, and the cost check, which reads particle.dt for the particle
    # side's estimate before any FE work)
    for name, path in import_closure(FE.runs).items():
        if name not in ("forcecal.scene", "forcecal.cost"):
            assert not re.search(r"\bscene\.(particle|calibration|outputs|verdict)\b",
                                 path.read_text()), name


def test_the_scenes_refusals_only_refuse_and_leave_every_key_alone(tmp_path):
    # what lets the keys leave them out: each returns nothing and assigns nothing but its
    # own locals (a Scene and its sections are frozen), so it can only raise
    from forcecal import scene as scene_module

    tree = ast.parse((ROOT / "forcecal" / "scene.py").read_text())
    functions = {node.name: node for node in tree.body if isinstance(node, ast.FunctionDef)}
    assert set(REFUSALS) <= set(functions)
    for name in REFUSALS:
        for node in ast.walk(functions[name]):
            assert not (isinstance(node, ast.Return) and node.value is not None), name
            targets = (node.targets if isinstance(node, ast.Assign)
                       else [node.target] if isinstance(node, (ast.AugAssign, ast.AnnAssign))
                       else [])
            assert all(isinstance(t, ast.Name) for t in targets), name
    assert dataclasses.fields(scene_module.Scene)  # a dataclass, and frozen:
    assert scene_module.Scene.__dataclass_params__.frozen
    # a changed refusal leaves the FE's and the calibration's keys as they were
    copy = tmp_path / "scene.py"
    source = (ROOT / "forcecal" / "scene.py").read_text()
    changed = source.replace("is shorter than \"\n                         f\"5 x tau_max",
                             "is below \"\n                         f\"5 x tau_max")
    assert changed != source
    copy.write_text(changed)
    for code in (FE, FIT):
        ignored = code.ignored_definitions()["forcecal.scene"]
        assert source_digest(copy, ignored) == source_digest(ROOT / "forcecal" / "scene.py",
                                                             ignored)
        assert source_digest(copy) != source_digest(ROOT / "forcecal" / "scene.py")


def test_fe_stage_code_is_the_fe_and_shared_packages():
    closure = import_closure(STAGES["reference"].code.runs)
    assert {"reference_fe.run", "reference_fe.model", "forcecal.h5io"} <= set(closure)
    assert not any(n.split(".")[0] in ("particle", "calibration") for n in closure)
    assert {n for n in closure if n.startswith("pipelines")} == {
        "pipelines", "pipelines.runners", "pipelines.runners.common", "pipelines.runners.reference"}
    declared = {f.split("/")[0] for f in STAGES["reference"].code.digests()}
    assert declared == {"reference_fe", "forcecal", "pipelines"}
    # the FE experiments' keys: the same FE code, without the pipeline's runner
    assert {f for f in STAGES["reference"].code.digests()
            if not f.startswith("pipelines")} == set(FE.digests())


def test_each_stage_key_holds_its_own_runner_only_and_the_report_the_scene_name(
        tmp_path, monkeypatch):
    from pipelines.runners.common import Context
    scene = scene_from_dict({"name": "keyed"})
    ctx = Context(scene, tmp_path, progress=False, ranks=1)
    for name in ("reference.h5", "params.h5", "gravity.h5"):
        (tmp_path / name).write_bytes(b"stand-in")
    monkeypatch.setattr("pipelines.stages.load_mesh", lambda scene: box_mesh((1, 1, 1), (1, 1, 1)))
    # the one-cell stand-in has no room for the scene's test points: the depth check that
    # builds them is stood in for (tested on real meshes in test_calibration_inputs)
    monkeypatch.setattr("pipelines.stages.build_problem", lambda scene, mesh: None)
    monkeypatch.setattr("pipelines.stages.check_experiment_depths", lambda scene, problem: None)
    # the stand-in is no HDF5 file: its experiments' content digest is stood in for too
    monkeypatch.setattr("pipelines.stages.reference_digest", lambda path, experiments: "ref")
    keys = {name: stage.inputs(ctx) for name, stage in STAGES.items()}
    for name, key in keys.items():
        runners = {f for f in key.code if f.startswith("pipelines/runners/")}
        assert runners == {"pipelines/runners/common.py", f"pipelines/runners/{name}.py"}
        assert "pipelines/stages.py" not in key.code
    renamed = STAGES["report"].inputs(Context(scene_from_dict({"name": "other"}), tmp_path,
                                              progress=False, ranks=1))
    assert renamed.changes_from({"scene": keys["report"].scene, "upstream": renamed.upstream,
                                 "code": renamed.code}) == ["scene [name] changed"]


@pytest.fixture
def project_copy(tmp_path, monkeypatch):
    """A copy of the project's packages in ``tmp_path``, which the code fingerprints read."""
    import shutil

    from forcecal import PROJECT_PACKAGES
    for package in PROJECT_PACKAGES:
        shutil.copytree(ROOT / package, tmp_path / package,
                        ignore=shutil.ignore_patterns("__pycache__"))
    monkeypatch.setattr("forcecal.provenance.package_root", lambda package: tmp_path)
    return tmp_path


def _stages_whose_code_changes(root, edits: dict[str, Callable[[str], str]]) -> list[str]:
    """The stages whose code fingerprint changes when the project copy in ``root`` is edited
    (``edits``: {file: function from its old to its new text})."""
    before = {name: stage.code.digests() for name, stage in STAGES.items()}
    for path, edit in edits.items():
        old = (root / path).read_text()
        (root / path).write_text(edit(old))
        assert (root / path).read_text() != old
    return [name for name, stage in STAGES.items()
            if StageInputs(code=stage.code.digests()).changes_from({"code": before[name]})]


def _comments_docstrings_layout(text: str) -> str:
    """``text`` with another module docstring, more comments and another layout."""
    first = text.index('"""') + 3
    text = text[:first] + "Reworded. " + text[first:]
    text = text.replace("from __future__ import annotations",
                        "# why: postponed annotations\nfrom __future__ import (\n    annotations)")
    return "# a comment first\n" + text + "\n\n# a comment last\n"


def _code_edit(text: str) -> str:
    return text + "\nEDITED = 1\n"


def test_a_comment_docstring_or_layout_edit_reruns_no_stage(project_copy):
    edited = [f"pipelines/runners/{m}.py" for m in ("common", "reference", "calibrate",
                                                     "gravity", "report")]
    edited += ["pipelines/gravity.py", "calibration/core.py", "reference_fe/model.py",
               "forcecal/scene.py", "particle/model.py"]
    assert _stages_whose_code_changes(
        project_copy, {path: _comments_docstrings_layout for path in edited}) == []


def test_editing_a_runner_reruns_its_stage_only(project_copy):
    for runner in ("reference", "calibrate", "gravity", "report"):
        assert _stages_whose_code_changes(
            project_copy, {f"pipelines/runners/{runner}.py": _code_edit}) == [runner]
    # what every runner imports changes every stage; the FE code the reference's only
    assert _stages_whose_code_changes(
        project_copy, {"pipelines/runners/common.py": _code_edit}) == list(STAGES)
    assert _stages_whose_code_changes(
        project_copy, {"reference_fe/model.py": _code_edit}) == ["reference"]
    assert _stages_whose_code_changes(
        project_copy, {"pipelines/report.py": _code_edit}) == ["report"]


def test_editing_code_outside_a_stage_declaration_reruns_no_stage(project_copy):
    # the package __init__ every module runs, the docs command, the cache, the CLI: none
    # can change a stage's outputs
    assert _stages_whose_code_changes(project_copy, {
        path: _code_edit for path in ("forcecal/__init__.py", "pipelines/__init__.py",
                                      "pipelines/docs.py", "pipelines/cache.py",
                                      "pipelines/cli.py", "pipelines/stages.py")}) == []
    # the FE code and the shared modules it reads rerun the reference; the particle model
    # every stage after it
    assert _stages_whose_code_changes(project_copy, {"reference_fe/run.py": _code_edit}) == [
        "reference"]
    assert _stages_whose_code_changes(project_copy, {"forcecal/mesh.py": _code_edit}) == list(
        STAGES)
    assert _stages_whose_code_changes(project_copy, {"particle/model.py": _code_edit}) == [
        "calibrate", "gravity", "report"]


def test_verbose_reaches_the_calibration(tmp_path, monkeypatch):
    import calibration
    from pipelines.runners.calibrate import Context, run_calibrate
    seen = {}
    monkeypatch.setattr(calibration, "calibrate", lambda *a, **kw: seen.update(kw))
    run_calibrate(Context(scene_from_dict({}), tmp_path, progress=False, ranks=1, verbose=True))
    assert seen == {"progress": False, "verbose": True}


def test_file_digest_of_missing_file_is_a_data_file_error(tmp_path):
    with pytest.raises(DataFileError, match="cannot read"):
        file_digest(tmp_path / "nope.h5")


# ------------------------------------------------------------------------------- gravity

def test_connector_strains_of_a_uniform_dilation_are_exact(column):
    model = build_model(column, 1000.0, linear_params(len(column.mesh.edges)))
    eps = 0.03
    strain = connector_strains(model, eps * column.mesh.vertices)
    # x -> (1 + eps) x scales every length by (1 + eps): strain eps to round-off
    assert np.allclose(strain, eps, rtol=0, atol=1e-12)


@pytest.fixture
def corner():
    """A 10 mm Kuhn-split cube with every vertex clamped but the corner (1, 1, 1) x 10 mm."""
    mesh = box_mesh((1, 1, 1), (0.01, 0.01, 0.01))
    free = int(np.argmax(mesh.vertices.sum(axis=1)))
    fixed = np.setdiff1d(np.arange(mesh.n_vertices), [free])
    return Problem(mesh=mesh, fixed=fixed, calibration=np.array([free]),
                   held_out=np.zeros(0, np.int64), tracked_node=free)


def test_gravity_runs_of_one_free_particle_match_the_closed_form(corner):
    """One particle on linear springs: static K^-1 m g, release (I - cos(w t)) per mode."""
    n = len(corner.mesh.edges)
    K0 = 100.0
    # arms 1e-6 x the springs: their stiffness and damping change the answer by ~1e-6
    params = ConnectorParams.uniform(n, K0=K0, k1=1e-6 * K0, b1=1e-6 * K0, k2=1e-6 * K0,
                                     b2=1e-5 * K0)
    g = np.array([0.0, 0.0, -0.01])  # sag ~1e-8 m on 10 mm springs: geometric terms ~1e-6
    scene = scene_from_dict({"particle": {"dt_safety": 0.05},
                             "gravity": {"acceleration": g.tolist()}})
    node = corner.tracked_node
    mass = corner.mesh.lumped_masses(scene.material.density)[node]
    ends = corner.mesh.edges[np.any(corner.mesh.edges == node, axis=1)]
    e = corner.mesh.vertices[ends[:, 1]] - corner.mesh.vertices[ends[:, 0]]
    e /= np.linalg.norm(e, axis=1)[:, None]
    stiffness = K0 * e.T @ e  # sum of K0 e e^T over the particle's springs [N/m]
    u_static = np.linalg.solve(stiffness, mass * g)
    lam, vec = np.linalg.eigh(stiffness / mass)
    period = 2 * np.pi / np.sqrt(lam.min())
    times = np.linspace(0.0, 2 * period, 81)
    modal = vec.T @ u_static
    u_exact = np.stack([vec @ ((1 - np.cos(np.sqrt(lam) * t)) * modal) for t in times])
    run, failure = gravity_outcome(scene, corner, params, times, (-0.5, 0.5), "calibrated")
    assert failure is None
    scale = np.abs(u_static).max()
    assert np.allclose(run.static_displacement[node], u_static, rtol=0, atol=1e-4 * scale)
    assert np.abs(np.delete(run.static_displacement, node, axis=0)).max() == 0.0
    # position Verlet at dt <= 0.05 x the limit (w dt <= 0.1): phase error (w dt)^2/24 per
    # radian, ~5e-3 rad after two periods of the slowest mode, so 1e-2 of the amplitude
    assert np.allclose(run.displacement[:, node], u_exact, rtol=0, atol=1e-2 * 2 * scale)
    assert run.dt <= 0.05 * run.critical_dt * (1 + 1e-12)
    assert abs(run.strain_max) < 1e-4 and abs(run.strain_min) < 1e-4


def test_gravity_runs_record_springs_invalid_on_the_calibrated_range(corner):
    n = len(corner.mesh.edges)
    # K(eps) = 100 (1 - 5 eps): positive on [-0.1, 0.1], zero at eps = 0.2, inside the release's
    # range (the tiny sag's strains +- particle.strain_margin = 0.2): the release is verified
    # on the range cut short of 0.2 instead (release_strain_range) and runs
    soft = ConnectorParams(K0=np.full(n, 100.0), a=np.full(n, -500.0), b=np.zeros(n),
                           k1=np.full(n, 50.0), b1=np.full(n, 5.0), k2=np.full(n, 20.0),
                           b2=np.full(n, 40.0))
    scene = scene_from_dict({"gravity": {"acceleration": [0.0, 0.0, -1.0]}})
    times = np.linspace(0.0, 0.01, 3)
    run, failure = gravity_outcome(scene, corner, soft, times, (-0.1, 0.1), "baseline")
    assert failure is None and np.all(np.isfinite(run.displacement))
    # refused before any load: a failure of the model (a result), not of the run
    run, failure = gravity_outcome(scene, corner, soft, times, (-0.5, 0.5), "baseline")
    assert run is None
    assert (failure.model, failure.experiment, failure.point, failure.reached) == (
        "baseline", "gravity_static", None, 0.0)
    assert re.search(r"ParameterError: .*K\(eps\).*<= 0 in the strain range", failure.reason)


@pytest.mark.parametrize("K0, a, b, lo, hi", [
    (100.0, -200.0, 0.0, -np.inf, 0.5),            # linear, softening in tension
    (100.0, 200.0, 0.0, -0.5, np.inf),             # linear, softening in compression
    (100.0, 0.0, 0.0, -np.inf, np.inf),            # constant
    (100.0, 0.0, 400.0, -np.inf, np.inf),          # stiffening, never zero
    (100.0, 0.0, -400.0, -0.5, 0.5),               # softening both ways
    (100.0, -50.0, 5.0, -np.inf, 5.0 - 5.0 ** 0.5),  # both roots in tension: the nearer one
    (100.0, 50.0, 5.0, -5.0 + 5.0 ** 0.5, np.inf),   # both roots in compression
])
def test_positive_spring_range_is_the_interval_between_the_nearest_roots(K0, a, b, lo, hi):
    from particle.stability import positive_spring_range
    params = ConnectorParams(K0=np.array([K0]), a=np.array([a]), b=np.array([b]),
                             k1=np.ones(1), b1=np.ones(1), k2=np.ones(1), b2=np.ones(1))
    got_lo, got_hi = positive_spring_range(params)
    np.testing.assert_allclose([got_lo[0], got_hi[0]], [lo, hi], rtol=1e-12)
    for eps in (got_lo[0], got_hi[0]):
        if np.isfinite(eps):
            assert abs(params.stiffness(np.array([eps]))[0]) < 1e-9 * K0


def test_gravity_file_round_trip_and_refusals(tmp_path, column):
    n, s = column.mesh.n_vertices, 4
    rng = np.random.default_rng(0)
    models = {m: GravityTest(rng.normal(size=(n, 3)), rng.normal(size=(s, n, 3)), 1e-4,
                                 2e-4, 0.1, 0.2, -0.05, 0.07)
              for m in ("calibrated", "baseline")}
    runs = GravityRuns(column, np.linspace(0, 0.03, s), np.array([0, 0, -9.81]), models,
                       "ref-sha", "params-sha")
    path = tmp_path / "gravity.h5"
    write_gravity(path, runs)
    back = read_gravity(path)
    assert back.reference_fingerprint == "ref-sha" and back.params_fingerprint == "params-sha"
    assert np.array_equal(back.time, runs.time)
    for m, r in models.items():
        assert np.array_equal(back.models[m].displacement, r.displacement)
        assert np.array_equal(back.models[m].static_displacement, r.static_displacement)
        assert (back.models[m].dt, back.models[m].strain_max) == (1e-4, 0.07)
    with h5py.File(path, "a") as fh:
        fh.attrs["experiments"] = "gravity_static, gravity_dynamic"
    with pytest.raises(DataFileError, match="attribute 'experiments'.*is not JSON"):
        read_gravity(path)
    write_gravity(path, runs)
    with h5py.File(path, "a") as fh:
        del fh["baseline"].attrs["dt"]
    with pytest.raises(DataFileError, match="baseline attribute 'dt' is missing"):
        read_gravity(path)
    path.write_bytes(path.read_bytes()[:200])
    with pytest.raises(DataFileError, match="not a readable HDF5 file"):
        read_gravity(path)
    with pytest.raises(DataFileError, match="does not exist"):
        read_gravity(tmp_path / "missing.h5")


# ------------------------------------------------------------------------------- report

def test_gravity_errors_closed_form():
    fe = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 0.0, -3.0]])
    free = np.array([False, True, True])
    # particle = 1.1 x FE: |du| = 0.1 |u_FE|; mean over free (0.1 + 0.3)/2 = 0.2, / max 3
    assert gravity_static_error(fe, 1.1 * fe, free) == pytest.approx(0.2 / 3.0, rel=1e-12)
    history = np.zeros((5, 3))
    history[:, 2] = -np.linspace(0, 2.0, 5)
    offset = np.array([0.3, 0.0, 0.4])  # |offset| = 0.5 at every sample: RMS 0.5, / max 2
    assert gravity_dynamic_error(history, history + offset) == pytest.approx(0.25, rel=1e-12)
    with pytest.raises(DataFileError, match="zero"):
        gravity_static_error(np.zeros((3, 3)), fe, free)
    with pytest.raises(DataFileError, match="zero"):
        gravity_dynamic_error(np.zeros((5, 3)), history)


def _report():
    return {"errors": dict.fromkeys(ERROR_KEYS, 0.1),
            "baseline_errors": dict.fromkeys(ERROR_KEYS, 0.2),
            "timings_s": dict.fromkeys(TIMING_KEYS, 1.0)}


def test_check_report_refuses_missing_and_non_finite_numbers():
    check_report(_report())
    r = _report()
    r["errors"]["indentation_held_out"] = None  # allowed: a scene without held-out points
    check_report(r)
    r = _report()
    r["errors"]["gravity_static"] = float("nan")
    with pytest.raises(DataFileError, match="errors.gravity_static = nan"):
        check_report(r)
    r = _report()
    del r["timings_s"]["calibration"]
    with pytest.raises(DataFileError, match="timings_s.calibration is missing"):
        check_report(r)
    # the force vector errors: absent (older reports) or null (older params.h5) pass, and
    # when present every curve key is checked as the normal errors' are
    r = _report()
    r["force_vector_errors"] = None
    check_report(r)
    r["force_vector_errors"] = {"calibrated": dict.fromkeys(CURVE_KEYS, 0.1)}
    check_report(r)
    r["force_vector_errors"]["calibrated"]["relaxation_held_out"] = None
    check_report(r)
    r["force_vector_errors"]["calibrated"]["relaxation_calibrated"] = float("inf")
    with pytest.raises(DataFileError, match="calibrated.relaxation_calibrated = inf"):
        check_report(r)
    del r["force_vector_errors"]["calibrated"]["relaxation_calibrated"]
    with pytest.raises(DataFileError, match="calibrated.relaxation_calibrated is missing"):
        check_report(r)
    # JSON of another shape: a list, or a group that is not an object
    with pytest.raises(DataFileError, match="report.json is a JSON list"):
        check_report([1, 2])
    for group, value in (("errors", [0.1]), ("force_vector_errors", "x"), ("not_run", 3)):
        r = _report()
        r[group] = value
        with pytest.raises(DataFileError, match=f"report.json: {group} = .* is not an object"):
            check_report(r)


# ------------------------------------------------------------------------------- fields

def test_xdmf_time_series_round_trip(tmp_path, column, monkeypatch):
    import meshio

    workdir = tmp_path / "cwd"
    workdir.mkdir()
    monkeypatch.chdir(workdir)
    from pipelines.fields import write_time_series
    n = column.mesh.n_vertices
    times = np.array([0.0, 0.1, 0.2])
    u = np.stack([t * np.tile([0.0, 0.0, -1.0], (n, 1)) for t in times])
    static = np.tile([0.0, 0.0, -0.5], (n, 1))
    out = tmp_path / "out"
    written = write_time_series(out / "g.xdmf", column.mesh, times, u, static)
    assert sorted(p.name for p in written) == ["g.h5", "g.xdmf"]
    assert sorted(os.listdir(out)) == ["g.h5", "g.xdmf"]  # no temporary left behind
    assert os.listdir(workdir) == [] and os.getcwd() == str(workdir)
    with meshio.xdmf.TimeSeriesReader(out / "g.xdmf") as reader:
        points, cells = reader.read_points_cells()
        assert np.allclose(points, column.mesh.vertices)
        assert np.array_equal(cells[0].data, column.mesh.tets)
        for k in range(reader.num_steps):
            t, point_data, _ = reader.read_data(k)
            assert t == pytest.approx(times[k])
            assert np.allclose(point_data["displacement"], u[k])
            assert np.allclose(point_data["static_displacement"], static)
    with pytest.raises(DataFileError, match="do not fit"):
        write_time_series(out / "bad.xdmf", column.mesh, times, u[:2], static)


def test_cli_reports_a_bad_scene_without_traceback(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text('[material]\nC10 = "soft"\n')
    r = subprocess.run([sys.executable, "-m", "pipelines", "demo", "--scene", str(bad),
                        "--out", str(tmp_path / "out")], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 2
    assert "error:" in r.stderr and "material.C10 = 'soft'" in r.stderr
    assert "Traceback" not in r.stderr
