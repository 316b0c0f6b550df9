"""Fault suite: hostile input and injected faults, each through a user-facing path.

Every case asserts what a user must see: exit code 2 (130/143 for Ctrl-C/SIGTERM),
exactly one ``error:`` line naming the cause (or the ``interrupted`` line), no
traceback, no file written outside the output folder, no half-written file
(``*.tmp-*``) left anywhere. Most cases run ``python -m pipelines`` in-process
(its ``main``) at scene- or mesh-load level, or with the stage's work replaced by an
injected fault, so the suite stays fast; two cases run real processes under mpirun
on the tiny scene. Groups:

* table of bad scenes: every scene key with a wrong type, every bound and choice
  violated (generated from the key declarations), plus the hand-written classes
  (names leaving runs/, Prony terms, zero gravity, too few records,
  encodings, absurd cost);
* bad mesh files (plain text, garbage, other units);
* fault injection: unexpected exceptions, disk full in every writer, Ctrl-C and
  SIGTERM, a locked output folder, stale temporaries, truncated FE parts, a
  NaN-filled reference offered for adoption, an unstable support, a non-physical
  model's stability limit, mpirun's boilerplate;
* property-based fuzzing (hypothesis) of scene files and meshes: any input is either
  accepted or refused with the project's error, never anything else.

Identical resumes after a kill are checked in test_calibration_fit.py
(test_interrupted_calibration_resumes_to_the_same_result,
test_killed_command_line_run_resumes_to_the_same_result: 1e-10 relative).
The number of cases run is printed at the end of the module.
"""
from __future__ import annotations

import dataclasses
import errno
import fcntl
import json
import logging
import math
import os
import re
import signal
import subprocess
import sys
import time
import tomllib
from pathlib import Path
from typing import Any, Union, get_args, get_origin, get_type_hints

import meshio
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from forcecal.errors import (ConvergenceError, DataFileError, MeshError,
                             ParameterError, SceneError, StabilityError)
from forcecal.failures import INTERRUPTED, Interrupted, run_command
from forcecal.mesh import box_mesh
from forcecal.scene import SECTIONS, load_scene
from pipelines import stages
from pipelines.cache import StageInputs
from pipelines.runners.common import Context
from pipelines.runners.reference import adopt_reference, run_mpirun
from pipelines.cli import main as pipelines_main
from tests.conftest import SCENES

TINY = tomllib.loads((SCENES / "tiny.toml").read_text())
CASES = {"table": 0, "fault": 0, "fuzz examples": 0}


@pytest.fixture(scope="module", autouse=True)
def _print_case_count(request):
    yield
    reporter = request.config.pluginmanager.get_plugin("terminalreporter")
    line = (f"fault suite: {CASES['table'] + CASES['fault']} cases ({CASES['table']} bad inputs, "
            f"{CASES['fault']} injected faults) + {CASES['fuzz examples']} fuzzed examples")
    capture = request.config.pluginmanager.getplugin("capturemanager")
    if reporter is None or capture is None:
        print(line)
        return
    with capture.global_and_fixture_disabled():  # past pytest's output capture
        reporter.write_line(line)


# ---------------------------------------------------------------------------- helpers

def toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return "nan" if math.isnan(v) else ("inf" if v == math.inf else
                                            "-inf" if v == -math.inf else repr(v))
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{json.dumps(k)} = {toml_value(x)}" for k, x in v.items()) + "}"
    if isinstance(v, str):
        return json.dumps(v)
    return str(v)


def toml_text(doc: dict) -> str:
    top = "".join(f"{json.dumps(k)} = {toml_value(v)}\n" for k, v in doc.items()
                  if not isinstance(v, dict))
    tables = "".join(f"\n[{json.dumps(k)}]\n" + "".join(f"{json.dumps(a)} = {toml_value(b)}\n"
                                                         for a, b in v.items())
                     for k, v in doc.items() if isinstance(v, dict))
    return top + tables


def tiny_with(**changes: dict) -> dict:
    doc = {k: (dict(v) if isinstance(v, dict) else v) for k, v in TINY.items()}
    for section, values in changes.items():
        if section == "top":
            doc.update(values)
        else:
            doc.setdefault(section, {}).update(values)
    return doc


def files_under(folder: Path) -> set[Path]:
    return {p for p in folder.rglob("*") if p.is_file()}


def run_refused(tmp_path: Path, capsys, argv_tail: list[str], cause: str, *, code: int = 2,
                stage: str = "reference", scene: Path | None = None) -> str:
    """Run ``python -m pipelines <stage>`` in-process from ``tmp_path``; assert the refusal."""
    out = tmp_path / "out"
    before = files_under(tmp_path)
    cwd = os.getcwd()
    os.chdir(tmp_path)
    handlers = logging.getLogger().handlers[:]
    try:
        argv = [stage, "--scene", str(scene or tmp_path / "scene.toml"), "--out", str(out),
                "--ranks", "1", "--no-progress", *argv_tail]
        got = pipelines_main(argv)
    finally:
        os.chdir(cwd)
        # the command's log handler writes to this test's captured stderr: drop it
        logging.getLogger().handlers[:] = handlers
    captured = capsys.readouterr()
    err = captured.err
    assert got == code, err
    assert "Traceback" not in err + captured.out
    if code == 2:
        lines = [line for line in err.splitlines() if line.startswith("error:")]
        assert len(lines) == 1, err
        assert re.search(cause, lines[0]), lines[0]
    else:
        assert err.strip().splitlines()[-1] == INTERRUPTED and "error:" not in err, err
    new = files_under(tmp_path) - before
    outside = [p for p in new if out not in p.parents]
    assert not outside, f"written outside the output folder: {outside}"
    assert not [p for p in tmp_path.rglob("*") if ".tmp-" in p.name], "half-written file left"
    return err


def scene_case(tmp_path, capsys, doc: dict | str | bytes, cause: str) -> str:
    path = tmp_path / "scene.toml"
    if isinstance(doc, dict):
        doc = toml_text(doc)
    path.write_bytes(doc if isinstance(doc, bytes) else doc.encode())
    CASES["table"] += 1
    return run_refused(tmp_path, capsys, [], cause)


# ---------------------------------------------------------------------------- bad scenes

def _wrong_type(tp: Any) -> Any:
    """A TOML value of the wrong type for a field of type ``tp``."""
    origin = get_origin(tp)
    if origin is Union:
        args = get_args(tp)
        if str in args and any(get_origin(a) is tuple for a in args):
            return 1.5
        if str in args and int in args:
            return 1.5
        return [1]  # str or float
    if origin is tuple or tp in (float, int):
        return "abc" if tp is not int else 2.5
    if tp is bool:
        return "yes"
    return 12  # str


def _generated_cases() -> list[tuple[str, dict, str]]:
    cases = []
    for section, cls in SECTIONS.items():
        hints = get_type_hints(cls)
        for f in dataclasses.fields(cls):
            where = re.escape(f"{section}.{f.name} = ")
            cases.append((f"{section}.{f.name} wrong type", {section: {f.name:
                          _wrong_type(hints[f.name])}}, where + r".*expected"))
            meta, tp = f.metadata, hints[f.name]
            if meta.get("minimum") is not None:
                bad = tp(meta["minimum"]) - 1
            elif meta.get("exclusive_minimum") is not None:
                bad = tp(meta["exclusive_minimum"])
            else:
                bad = None
            if bad is not None and tp in (float, int):
                cases.append((f"{section}.{f.name} out of range", {section: {f.name: bad}},
                              where + r".*must be (>|>=) "))
            if meta.get("choices"):
                cases.append((f"{section}.{f.name} not a choice",
                              {section: {f.name: "nonsense"}}, where + r".*must be one of"))
    return cases


GENERATED = _generated_cases()


@pytest.mark.parametrize("name, change, cause", GENERATED, ids=[c[0] for c in GENERATED])
def test_every_key_refuses_a_wrong_type_or_range(name, change, cause, tmp_path, capsys):
    scene_case(tmp_path, capsys, tiny_with(**change), cause)


HAND_WRITTEN = {
    # names that would leave runs/ or write into it
    "name ..": (tiny_with(top={"name": ".."}), r"name = '\.\.' .*inside runs/"),
    "name .": (tiny_with(top={"name": "."}), r"name = '\.' must be"),
    "hidden name": (tiny_with(top={"name": ".git"}), r"name = '\.git' must be"),
    "nested name": (tiny_with(top={"name": "a/../../b"}), r"without slashes"),
    "backslash name": (tiny_with(top={"name": "a\\b"}), r"without slashes"),
    "name with space": (tiny_with(top={"name": "my organ"}), r"without slashes or spaces"),
    "empty name": (tiny_with(top={"name": ""}), r"name = '' must be"),
    "numeric name": (tiny_with(top={"name": 5}), r"name = 5 must be"),
    "name with newline": (tiny_with(top={"name": "a\nb"}), r"must be"),
    # Prony terms the model has (2)
    "no Prony terms": (tiny_with(material={"prony_g": [], "prony_tau": []}),
                       r"material.prony_g has 0 term\(s\); .*exactly 2 Maxwell arms"),
    "one Prony term": (tiny_with(material={"prony_g": [0.3], "prony_tau": [1.0]}),
                       r"has 1 term\(s\)"),
    "three Prony terms": (tiny_with(material={"prony_g": [0.2, 0.2, 0.2],
                                              "prony_tau": [0.2, 0.5, 1.0]}),
                          r"has 3 term\(s\)"),
    "Prony lengths differ": (tiny_with(material={"prony_g": [0.3, 0.2], "prony_tau": [1.0]}),
                             r"differ in length"),
    "Prony sum >= 1": (tiny_with(material={"prony_g": [0.6, 0.5]}), r"must be < 1"),
    "negative Prony time": (tiny_with(material={"prony_tau": [-0.2, 1.0]}), r"must be > 0"),
    # gravity and records
    "zero gravity": (tiny_with(gravity={"acceleration": [0.0, 0.0, 0.0]}),
                     r"gravity.acceleration = \[0.0, 0.0, 0.0\].*non-zero gravity"),
    "duration of one record": (tiny_with(gravity={"duration": 0.004}),
                               r"gravity.duration = 0.004 s holds 1 record"),
    "duration of 3 records": (tiny_with(gravity={"duration": 0.01}),
                              r"holds 3 record\(s\).*at least 4"),
    "record interval above fe_dt": (tiny_with(gravity={"fe_dt": 0.01,
                                                       "record_interval": 0.005}),
                                    r"gravity.record_interval .* shorter than gravity.fe_dt"),
    "gravity of 2 components": (tiny_with(gravity={"acceleration": [0.0, -9.81]}),
                                r"gravity.acceleration = .*expected list of 3"),
    "infinite gravity": (tiny_with(gravity={"acceleration": [0.0, 0.0, -math.inf]}),
                         r"gravity.acceleration = .*expected"),
    "NaN density": (tiny_with(material={"density": math.nan}), r"material.density = nan"),
    "hold shorter than 5 tau": (tiny_with(relaxation={"hold_time": 1.0, "hold_steps": 2}),
                                r"shorter than 5 x tau_max"),
    "hold steps do not fit": (tiny_with(relaxation={"hold_steps": 200}),
                              r"relaxation.hold_steps"),
    "particle.dt word": (tiny_with(particle={"dt": "fast"}), r"particle.dt must be 'auto'"),
    "particle.dt negative": (tiny_with(particle={"dt": -1e-4}), r"particle.dt = -0.0001 must"),
    "test points word": (tiny_with(test_points={"calibration": "some"}),
                         r"test_points.calibration must be 'auto'"),
    "unknown table": (tiny_with(top={"materials": {"C10": 1.0}}), r"unknown top-level"),
    "unknown key": (tiny_with(mesh={"sorce": "generate"}), r"unknown key\(s\) \['sorce'\]"),
    "section not a table": (tiny_with(top={"fe": 3}), r"\[fe\] must be a table"),
    "description not text": (tiny_with(top={"description": 3}), r"description must be"),
    # encodings and files
    "latin-1 scene": ('name = "f\xe9e"\n'.encode("latin-1"), r"not UTF-8 text \(byte 9: invalid continuation byte\)"),
    "UTF-16 scene": ('name = "x"\n'.encode("utf-16"), r"not UTF-8 text"),
    "binary scene": (bytes(range(256)), r"not UTF-8 text|not valid TOML"),
    "TOML syntax": ("[mesh\nsource = 1\n", r"not valid TOML"),
    "TOML duplicate key": ("name = 'a'\nname = 'b'\n", r"not valid TOML"),
    "empty list of tables": ("[[mesh]]\n", r"\[mesh\] must be a table"),
    # cost estimate: absurd work, refused with the estimate and the key
    "indentation.steps 1e7": (tiny_with(indentation={"steps": 10_000_000}),
                              r"FE reference would take about .* vertex-steps .* "
                              r"change indentation.steps"),
    "relaxation steps 1e7": (tiny_with(relaxation={"hold_steps": 10_000_000,
                                                   "hold_time": 1e9}),
                             r"change relaxation.hold_steps"),
    "gravity.fe_dt 1e-9": (tiny_with(gravity={"fe_dt": 1e-9}), r"change gravity.fe_dt"),
    "particle.dt 1e-9": (tiny_with(particle={"dt": 1e-9}),
                         r"particle gravity release would take about .* connector-steps.*"
                         r"change particle.dt"),
    # meshes
    "missing mesh file": (tiny_with(mesh={"source": "nowhere.vtu"}), r"does not exist"),
    "mesh is a folder": (tiny_with(mesh={"source": "."}), r"is a directory, not a file"),
}


@pytest.mark.parametrize("case", HAND_WRITTEN)
def test_hostile_scenes_are_refused_before_any_work(case, tmp_path, capsys):
    doc, cause = HAND_WRITTEN[case]
    scene_case(tmp_path, capsys, doc, cause)


def test_missing_and_directory_scene_files(tmp_path, capsys):
    for scene, cause in ((tmp_path / "nope.toml", r"does not exist"),
                         (tmp_path, r"is a directory, not a file")):
        CASES["table"] += 1
        run_refused(tmp_path, capsys, [], cause, scene=scene)


BOX = box_mesh((2, 2, 2), (0.03, 0.03, 0.03))


def _mesh_file(kind: str, folder: Path) -> str:
    if kind == "plain text .msh":
        (folder / "m.msh").write_text("this is not a mesh\n")
        return "m.msh"
    if kind == "plain text .vtu":
        (folder / "m.vtu").write_text("hello\n")
        return "m.vtu"
    if kind == "garbage .vtk":
        (folder / "m.vtk").write_bytes(os.urandom(300))
        return "m.vtk"
    if kind == "unknown extension":
        (folder / "m.xyz").write_text("1 2 3\n")
        return "m.xyz"
    if kind == "truncated .msh":
        meshio.write(folder / "full.msh", meshio.Mesh(BOX.vertices, [("tetra", BOX.tets)]),
                     file_format="gmsh22", binary=False)
        text = (folder / "full.msh").read_text()
        (folder / "m.msh").write_text(text[:len(text) // 2])
        return "m.msh"
    # a 30 mm box written in mm; or in metres (but scaled as if in mm by the scene)
    scale = {"mesh in mm": 1000.0, "mesh scaled twice": 1.0}[kind]
    meshio.write(folder / "m.vtu", meshio.Mesh(BOX.vertices * scale, [("tetra", BOX.tets)]))
    return "m.vtu"


MESH_CASES = {"plain text .msh": r"meshio could not read it",
              "plain text .vtu": r"meshio could not read it",
              "garbage .vtk": r"meshio could not read it",
              "unknown extension": r"meshio could not read it",
              "truncated .msh": r"meshio could not read it|m.msh",
              "mesh in mm": r"bounding-box diagonal 5[0-9.]+ m.*set mesh.scale \(e.g. mesh.scale "
                            r"= 0.001\)",
              "mesh scaled twice": r"with mesh.scale = 0.001\): not an organ's size in metres"
                                   r".*mesh.scale = 1\)"}


@pytest.mark.parametrize("kind", MESH_CASES)
def test_bad_mesh_files_are_refused_with_the_cause(kind, tmp_path, capsys):
    name = _mesh_file(kind, tmp_path)
    doc = tiny_with(mesh={"source": name, "scale": 0.001 if kind == "mesh scaled twice" else 1.0},
                    fixed={"tolerance": 1e-4})
    scene_case(tmp_path, capsys, doc, MESH_CASES[kind])


# ---------------------------------------------------------------------------- injected faults

def _inject(monkeypatch, run) -> None:
    """Replace the reference stage's work by ``run(ctx)`` (no mesh, no FE)."""
    fake = dataclasses.replace(stages.STAGES["reference"], run=run, reads_mesh=False)
    monkeypatch.setitem(stages.STAGES, "reference", fake)


def _raise(exc: BaseException):
    def run(ctx):
        (ctx.out / "reference.h5.parts").mkdir(exist_ok=True)
        raise exc
    return run


FAULTS = {
    "scipy-like ValueError": (ValueError("array must not contain infs or NaNs"),
                              r"unexpected ValueError: array must not contain infs.*"
                              r"\[stage reference; kept: nothing\]"),
    "reference.h5 is a directory": (IsADirectoryError(errno.EISDIR, "Is a directory",
                                                      "runs/x/reference.h5"),
                                    r"cannot access runs/x/reference.h5: Is a directory"),
    "permission denied": (PermissionError(errno.EACCES, "Permission denied", "/root/x"),
                          r"cannot access /root/x: Permission denied"),
    "I/O error": (OSError(errno.EIO, "Input/output error"), r"input/output error"),
    "out of memory": (MemoryError(), r"out of memory"),
    "KeyError": (KeyError("x"), r"unexpected KeyError: 'x'"),
    "IndexError": (IndexError("index 1 is out of bounds"), r"unexpected IndexError"),
    "ZeroDivisionError": (ZeroDivisionError("float division by zero"),
                          r"unexpected ZeroDivisionError"),
    "RuntimeError": (RuntimeError("PETSc error 76"), r"unexpected RuntimeError: PETSc error"),
    "AssertionError": (AssertionError("shape"), r"unexpected AssertionError"),
    "TypeError": (TypeError("bad operand"), r"unexpected TypeError"),
    "multi-line message": (ValueError("first\nsecond"), r"first second"),
    "ConvergenceError": (ConvergenceError("indentation-0003: step 4/10 did not converge"),
                         r"^error: indentation-0003: step 4/10 did not converge \[stage "),
    "StabilityError": (StabilityError("gravity static: unstable support"),
                       r"unstable support"),
    "DataFileError": (DataFileError("x.h5 is truncated"), r"x.h5 is truncated"),
}


@pytest.mark.parametrize("case", FAULTS)
def test_any_exception_in_a_stage_ends_with_one_error_line(case, tmp_path, capsys,
                                                           monkeypatch):
    exc, cause = FAULTS[case]
    _inject(monkeypatch, _raise(exc))
    (tmp_path / "scene.toml").write_text(toml_text(TINY))
    CASES["fault"] += 1
    run_refused(tmp_path, capsys, [], cause)


@pytest.mark.parametrize("signal_exc, code", [(KeyboardInterrupt(), 130),
                                              (Interrupted(signal.SIGTERM), 143)])
def test_interrupt_ends_with_the_resume_line(signal_exc, code, tmp_path, capsys, monkeypatch):
    _inject(monkeypatch, _raise(signal_exc))
    (tmp_path / "scene.toml").write_text(toml_text(TINY))
    CASES["fault"] += 1
    run_refused(tmp_path, capsys, [], "", code=code)


def _enospc(*args, **kwargs):
    raise OSError(errno.ENOSPC, "No space left on device")


def _partial_then_full(self, data, *args, **kwargs):
    with open(self, "w") as fh:
        fh.write(data[:10])  # some bytes reach the disk, then it is full
    _enospc()


def _disk_full_writers():
    from forcecal import h5io

    def report(ctx, monkeypatch):  # write_report's own writer, after its content checks
        monkeypatch.setattr(Path, "write_text", _partial_then_full)
        with h5io.atomic_path(ctx.out / "report.json") as tmp:
            tmp.write_text(json.dumps({"errors": {}}))

    def h5(ctx, monkeypatch):
        real = h5io.h5py.File

        def file(path, mode="r", *a, **k):
            fh = real(path, mode, *a, **k)
            if mode == "w":
                fh.close()
                _enospc()
            return fh
        monkeypatch.setattr(h5io.h5py, "File", file)
        with h5io.atomic_h5(ctx.out / "reference.h5", "forcecal.reference", 1) as fh:
            fh["x"] = np.zeros(3)

    def figure(ctx, monkeypatch):
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        from matplotlib.figure import Figure
        monkeypatch.setattr(Figure, "savefig", lambda self, tmp, **k: (
            Path(tmp).write_bytes(b"\x89PNG"), _enospc()))
        fig = plt.figure()
        with h5io.atomic_path(ctx.out / "figures" / "f.png") as tmp:
            fig.savefig(tmp)
        plt.close(fig)

    def checkpoint(ctx, monkeypatch):
        from calibration.checkpoint import Checkpoint
        monkeypatch.setattr(Path, "write_text", _partial_then_full)
        Checkpoint(ctx.out / "checkpoints" / "params.h5.json", {"a": "b"}).put("x", [1.0])

    return {"report.json": (report, r"cannot write .*report.json: No space left on device"),
            "reference.h5": (h5, r"cannot write .*reference.h5: No space left on device"),
            "figure": (figure, r"cannot write .*f.png: No space left"),
            "checkpoint": (checkpoint, r"cannot write .*params.h5.json: No space left")}


DISK_FULL = _disk_full_writers()


@pytest.mark.parametrize("writer", DISK_FULL)
def test_disk_full_leaves_nothing_half_written(writer, tmp_path, capsys, monkeypatch):
    write, cause = DISK_FULL[writer]
    _inject(monkeypatch, lambda ctx: write(ctx, monkeypatch))
    (tmp_path / "scene.toml").write_bytes(toml_text(TINY).encode())
    CASES["fault"] += 1
    run_refused(tmp_path, capsys, [], cause)
    assert not (tmp_path / "out" / "reference.h5").exists()
    assert not (tmp_path / "out" / "report.json").exists()


def test_a_locked_output_folder_refuses_a_second_run(tmp_path, capsys, monkeypatch):
    _inject(monkeypatch, lambda ctx: ["reference.h5"])
    (tmp_path / "scene.toml").write_text(toml_text(TINY))
    out = tmp_path / "out"
    out.mkdir()
    with open(out / stages.LOCK, "a+") as held:
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)  # another run holds the folder
        CASES["fault"] += 1
        run_refused(tmp_path, capsys, [], r"in use by another forcecal run")


def test_stale_temporaries_are_removed_on_the_next_start(tmp_path, capsys, monkeypatch):
    out = tmp_path / "out"
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True).stdout.strip()  # a pid that is gone
    stale = [out / f"reference.h5.tmp-{dead}", out / "figures" / f"a.png.tmp-{dead}"]
    live = out / f"params.h5.tmp-{os.getpid()}"  # a live writer's file is kept
    for p in stale + [live]:
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(b"half")

    def write(ctx):
        (ctx.out / "reference.h5").write_bytes(b"x")
        return ["reference.h5"]
    _inject(monkeypatch, write)
    (tmp_path / "scene.toml").write_text(toml_text(TINY))
    CASES["fault"] += 1
    handlers = logging.getLogger().handlers[:]
    assert pipelines_main(["reference", "--scene", str(tmp_path / "scene.toml"), "--out",
                           str(out), "--ranks", "1", "--no-progress"]) == 0
    logging.getLogger().handlers[:] = handlers
    assert not any(p.exists() for p in stale) and live.exists()
    live.unlink()


def test_truncated_fe_parts_are_discarded_and_recomputed(tmp_path, caplog):
    from reference_fe.run import WorkItem, _Parts
    parts = _Parts(tmp_path / "reference.h5", "key")
    parts.start()
    items = [WorkItem("indentation", p, 1.0) for p in range(3)]
    for it in items:
        parts.save(it, {"force": np.ones((4, 3))})
    whole = parts.path(items[0]).read_bytes()
    parts.path(items[0]).write_bytes(whole[:len(whole) // 2])  # truncated (BadZipFile)
    parts.path(items[1]).write_bytes(b"")  # empty
    CASES["fault"] += 2
    with caplog.at_level("WARNING"):
        assert parts.load(items[0]) is None and parts.load(items[1]) is None
    assert "discarding the unreadable checkpoint part" in caplog.text
    assert not parts.path(items[0]).exists() and not parts.path(items[1]).exists()
    np.testing.assert_array_equal(parts.load(items[2])["force"], np.ones((4, 3)))


def test_nan_filled_reference_is_not_adopted(tmp_path, monkeypatch):
    """A reference.h5 whose fingerprints match but whose curves are NaN: refused at adoption,
    naming --force, instead of failing every later stage."""
    import h5py

    from forcecal.h5io import write_reference
    from pipelines.cache import Cache
    scene = load_scene(SCENES / "tiny.toml")
    ctx = Context(scene, tmp_path, False, 1)
    reference = _fake_reference(scene)
    write_reference(tmp_path / "reference.h5", reference)
    with h5py.File(tmp_path / "reference.h5", "r+") as fh:
        fh["indentation/force"][0, 0, 0] = np.nan
    inputs = StageInputs(scene={}, mesh=reference.problem.mesh.fingerprint(), upstream={},
                                code={})
    CASES["fault"] += 1
    with pytest.raises(DataFileError, match=r"cannot be adopted: .*(NaN|non-finite).*"
                       r"reference --force") as info:
        adopt_reference(ctx, inputs.mesh)
    assert Cache(tmp_path).check("reference", inputs)  # not recorded as done
    # the error line must not offer the refused file for a resume ("rerun ... to resume")
    from forcecal.failures import describe, note_stage
    line = describe(note_stage(info.value, "reference", "reference.h5; rerun the same command "
                               "to resume"))
    assert line.endswith("[stage reference; kept: nothing]") and "resume" not in line, line


def test_reference_without_keys_or_with_other_keys_is_not_adopted(tmp_path):
    """Adoption decides from the experiment keys (scene sections, mesh, FE code fingerprints):
    a file that records none, or other ones, is recomputed, whatever its age."""
    from forcecal.h5io import write_reference
    scene = load_scene(SCENES / "tiny.toml")
    ctx = Context(scene, tmp_path, False, 1)
    reference = _fake_reference(scene)
    mesh = reference.problem.mesh.fingerprint()
    write_reference(tmp_path / "reference.h5", reference)
    assert adopt_reference(ctx, mesh)  # the keys match and the content is valid
    keys = json.loads(reference.meta["experiment_keys"])
    for stored in ({}, {**keys, "relaxation": "computed by other FE code"}):
        meta = {**reference.meta, "experiment_keys": json.dumps(stored)}
        write_reference(tmp_path / "reference.h5", dataclasses.replace(reference, meta=meta))
        assert not adopt_reference(ctx, mesh)


def _fake_reference(scene):
    """A schema-valid reference of the tiny scene with synthetic curves (no FE)."""
    from forcecal.h5io import GravityResult, IndentationCurves, Reference, RelaxationCurves
    from forcecal.problem import build_problem
    from forcecal.schedules import indentation_depths, record_times, relaxation_schedule
    from forcecal.sections import REFERENCE_SECTIONS
    from reference_fe.keys import experiment_keys
    problem = build_problem(scene)
    n, p = problem.mesh.n_vertices, len(problem.test_points)
    depths = indentation_depths(scene.indentation)
    times, rdepths = relaxation_schedule(scene.relaxation)
    f_ind = np.einsum("s,pk->psk", depths * 100.0, problem.normals)
    f_rel = np.einsum("s,pk->psk", rdepths * 100.0, problem.normals)
    g = scene.gravity
    t = record_times(g.duration, g.record_interval)
    meta = {"dolfinx_version": "0.5.2",
            "scene_fingerprint": scene.fingerprint(*REFERENCE_SECTIONS),
            "mesh_fingerprint": problem.mesh.fingerprint(),
            "timings_s": json.dumps({"total": 1.0}), "n_ranks": 1,
            "experiment_keys": json.dumps(experiment_keys(scene, problem.mesh.fingerprint()))}
    return Reference(
        problem=problem, material=scene.material,
        indentation=IndentationCurves(depths, f_ind, depths * 100.0 * np.ones((p, 1))),
        relaxation=RelaxationCurves(times, rdepths, f_rel, rdepths * 100.0 * np.ones((p, 1))),
        gravity=GravityResult(static_displacement=np.zeros((n, 3)), time=t,
                              displacement=np.zeros((len(t), n, 3)),
                              settings=dataclasses.replace(g, tracked_node=problem.tracked_node)),
        meta=meta, fe=scene.fe)


@pytest.mark.parametrize("sag, factor, first, cause", [
    (0.066, 0.25, 0.002 / 0.25, r"unstable support: the sag grows much faster than the load"),
    # more than half the body, proportionally to the load: not called a runaway sag
    (0.3, 1.0, 0.29, r"gravity static: the support does not hold the body: the sag reaches "
                     r"more than half the body's size \(300 mm at 1 x gravity, body size 200 mm"),
])
def test_unstable_support_is_named(sag, factor, first, cause):
    from reference_fe.experiments import check_sag
    CASES["fault"] += 1
    with pytest.raises(StabilityError, match=cause) as info:
        check_sag(sag, factor, first, 0.2, 5)
    assert "5 fixed vertices of the [fixed] section" in str(info.value)
    assert ("grows much faster" in str(info.value)) == (sag / factor / first > 5.0)
    check_sag(0.004, 1.0, 0.0039, 0.2, 5)  # a sound support: nearly linear
    with pytest.raises(StabilityError, match=r"^the weight along \[1.0, 0.0, 0.0\] \(static\): "):
        check_sag(sag, factor, first, 0.2, 5, what="the weight along [1.0, 0.0, 0.0] (static)")


@pytest.mark.parametrize("moved, static, cause", [
    # 3.5 x the static sag: beyond the linear bound of twice it and the margin above it
    (0.021, 0.006, r"gravity dynamic: the release has moved the body by 21 mm at 1.4 s, 3.50 x "
                   r"its static sag of 6 mm .*: it falls over or buckles"),
    # no static sag known: only the body's size
    (0.21, None, r"gravity dynamic: the release has moved the body by 210 mm at 1.4 s, more "
                 r"than its size \(200 mm\)"),
])
def test_a_release_the_support_does_not_hold_is_named(moved, static, cause):
    from reference_fe.experiments import RELEASE_RUNAWAY_LIMIT, check_release
    CASES["fault"] += 1
    with pytest.raises(StabilityError, match=cause) as info:
        check_release(moved, 1.4, static, 0.2, 5, "fixed", "gravity dynamic")
    assert info.value.reached == 1.4
    assert "5 fixed vertices of the [fixed] section do not hold the body in motion" in str(
        info.value)
    # a release that swings about its sag (the linear bound: twice the static sag) goes on
    check_release(2.0 * 0.006, 1.4, 0.006, 0.2, 5, "fixed", "gravity dynamic")
    check_release(RELEASE_RUNAWAY_LIMIT * 0.006, 1.4, 0.006, 0.2, 5, "fixed", "gravity dynamic")
    # with the static sag known, the body's size does not matter (a sag near half of it
    # swings further); without it, a release within the body's size goes on
    check_release(0.15, 1.4, 0.09, 0.2, 5, "fixed", "gravity dynamic")
    check_release(0.2, 1.4, None, 0.2, 5, "fixed", "gravity dynamic")


def test_a_failed_item_stops_the_other_ranks_at_their_next_step():
    """The FE ranks ask the stop check (another rank's FAILED note) before every load or time
    step: a long item is abandoned at its next step, not finished."""
    from reference_fe import experiments

    @dataclasses.dataclass
    class State:
        progress: float

    failed = {"now": False}
    steps = []

    def step(state, previous, target):
        steps.append(target)
        if len(steps) == 3:
            failed["now"] = True  # another rank fails while this one is at its third step
        return State(target)

    experiments.set_stop_check(lambda: failed["now"])
    CASES["fault"] += 1
    try:
        with pytest.raises(experiments.Stopped):
            list(experiments.march(State(0.0), np.arange(1.0, 1001.0), step, max_cuts=0,
                                   what="gravity dynamic", unit="s"))
    finally:
        experiments.set_stop_check(None)
    assert len(steps) == 3  # not 1000


def test_stability_limit_of_a_model_with_negative_k0_is_refused():
    from particle.stability import critical_time_step
    from particle.model import build_model
    from particle.params import viscoelastic_params
    from forcecal.problem import Problem
    fixed = np.nonzero(np.isclose(BOX.vertices[:, 2], 0.0))[0]
    problem = Problem(BOX, fixed, np.zeros(0, np.int64), np.zeros(0, np.int64), 26)
    params = viscoelastic_params(len(BOX.edges), 50.0)
    K0 = params.K0.copy()
    K0[7] = -1.0
    model = build_model(problem, 1000.0, dataclasses.replace(params, K0=K0))
    CASES["fault"] += 1
    with pytest.raises(ParameterError, match=r"connector 7 \(particles \d+-\d+\)"):
        critical_time_step(model)


MPIRUN_TEXT = """\
[rank 1] WARNING reference_fe.run: a rank's own log line
error: indentation-0002: step 3/10 did not converge
--------------------------------------------------------------------------
Primary job  terminated normally, but 1 process returned
a non-zero exit code. Per user-direction, the job has been aborted.
--------------------------------------------------------------------------
--------------------------------------------------------------------------
mpirun detected that one or more processes exited with non-zero status, thus causing
the job to be terminated. The first process to do so was:

  Process name: [[1234,1],0]
  Exit code:    2
--------------------------------------------------------------------------
[host:01234] 1 more process has sent help message help-mpi-api.txt / mpi-abort
"""


@pytest.mark.parametrize("text, error, shown", [
    (MPIRUN_TEXT, "indentation-0002: step 3/10 did not converge",
     "[rank 1] WARNING reference_fe.run: a rank's own log line"),
    (MPIRUN_TEXT.replace("error: ", "[rank 1] error: "),
     "indentation-0002: step 3/10 did not converge", "a rank's own log line"),
    (MPIRUN_TEXT.replace("error: indentation-0002: step 3/10 did not converge\n", ""), None,
     "a rank's own log line"),
])
def test_mpirun_boilerplate_is_kept_for_the_log(text, error, shown, tmp_path, capfd, caplog):
    script = tmp_path / "fake_mpirun.py"
    script.write_text(f"import sys\nsys.stderr.write({text!r})\nsys.exit(2)\n")
    CASES["fault"] += 1
    with caplog.at_level("DEBUG", logger="pipelines.runners.reference"):
        rc, message = run_mpirun([sys.executable, str(script)])
    err = capfd.readouterr().err
    assert rc == 2 and message == error
    assert shown in err
    assert "Primary job" not in err and "mpirun detected" not in err and "-----" not in err
    assert "error:" not in err
    assert "Primary job" in caplog.text  # kept for --verbose


@pytest.mark.parametrize("rc, said", [(137, "137 is a rank killed (SIGKILL), most often for "
                                             "want of memory: fewer ranks (--ranks)"),
                                       (2, "mpirun exit code 2; --verbose")])
def test_a_rank_killed_by_the_system_is_named_as_such(rc, said, tmp_path, monkeypatch):
    """mpirun ending with 137 (a rank sent SIGKILL: on Linux the out-of-memory killer; seen
    with two ranks of refined punch models next to another job) says so and what needs less
    memory; another code is given as it is."""
    import types

    from pipelines.runners import reference as runner
    CASES["fault"] += 1
    monkeypatch.setattr(runner, "run_mpirun", lambda cmd: (rc, None))
    monkeypatch.setattr(runner.shutil, "which", lambda name: "/usr/bin/mpirun")
    ctx = types.SimpleNamespace(out=tmp_path, under_mpi=False, ranks=2, progress=False,
                                scene=types.SimpleNamespace(path=tmp_path / "scene.toml"),
                                problem=None)
    with pytest.raises(runner.StageFailed, match=re.escape(said)) as info:
        runner.run_reference(ctx)
    assert ("SIGKILL" in str(info.value)) == (rc == 137)


def test_describe_names_every_kind_of_failure():
    from forcecal.failures import describe, note_stage
    CASES["fault"] += 1
    exc = note_stage(SceneError("bad"), "calibrate", "reference.h5")
    assert describe(exc) == "bad [stage calibrate; kept: reference.h5]"
    assert run_command(lambda: 0) == 0


# ---------------------------------------------------------------------------- real processes

def _tiny_scene(tmp_path: Path, **changes) -> Path:
    path = tmp_path / "scene.toml"
    path.write_text(toml_text(tiny_with(**changes)))
    return path


def _descendants(pid: int) -> set[int]:
    """Live descendants of ``pid`` (mpirun and its ranks), from every process's parent id
    (``/proc/<p>/stat``: also the children a non-main thread started)."""
    parent = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        parent[int(stat.parent.name)] = int(fields[1])
    found, todo = set(), [pid]
    while todo:
        p = todo.pop()
        for child in [c for c, pp in parent.items() if pp == p and c not in found]:
            found.add(child)
            todo.append(child)
    return found


def _alive(pids: set[int]) -> set[int]:
    alive = set()
    for p in pids:
        try:
            state = Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:
            continue
        if state != "Z":
            alive.add(p)
    return alive


@pytest.mark.skipif(not __import__("shutil").which("mpirun"), reason="needs mpirun")
def test_a_rank_refusal_shows_one_error_line_without_mpirun_text(tmp_path):
    """Every FE step fails (one Newton iteration, no cuts): the spawned ranks refuse, the user
    sees the project's error line once and none of mpirun's text."""
    scene = _tiny_scene(tmp_path, fe={"newton_max_it": 1, "max_step_cuts": 0})
    CASES["fault"] += 1
    r = subprocess.run([sys.executable, "-m", "pipelines", "reference", "--scene", str(scene),
                        "--out", str(tmp_path / "out"), "--ranks", "2", "--no-progress"],
                       capture_output=True, text=True, cwd=tmp_path, timeout=600)
    assert r.returncode == 2, r.stderr[-3000:]
    lines = [line for line in r.stderr.splitlines() if "error:" in line]
    assert len(lines) == 1 and lines[0].startswith("error: FE reference failed: "), r.stderr
    assert "did not converge" in lines[0] and "[stage reference; kept:" in lines[0]
    for boilerplate in ("Primary job", "mpirun detected", "-----", "Traceback"):
        assert boilerplate not in r.stderr, r.stderr
    assert not list(tmp_path.rglob("*.tmp-*"))


def _default_sigint() -> None:
    """Ctrl-C's disposition in the child, as in a user's terminal: a test run started in the
    background by a non-interactive shell has SIGINT ignored, and children inherit that."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.mark.skipif(not __import__("shutil").which("mpirun"), reason="needs mpirun")
@pytest.mark.parametrize("sig, code", [(signal.SIGINT, 130), (signal.SIGKILL, -signal.SIGKILL)])
def test_stopping_the_pipeline_ends_its_mpi_ranks(sig, code, tmp_path):
    """Ctrl-C (SIGINT to the pipeline) ends it with the resume line and exit 130; SIGKILL
    ends it at once; either way no spawned mpirun rank survives it."""
    scene = _tiny_scene(tmp_path)
    out = tmp_path / "out"
    CASES["fault"] += 1
    run = subprocess.Popen([sys.executable, "-m", "pipelines", "reference", "--scene",
                            str(scene), "--out", str(out), "--ranks", "2", "--no-progress"],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                           cwd=tmp_path, preexec_fn=_default_sigint)
    try:
        deadline = time.monotonic() + 300  # a hang guard, not a timing assert
        spawned: set[int] = set()
        while time.monotonic() < deadline and run.poll() is None:
            spawned = _descendants(run.pid)
            if len(spawned) >= 3 and (out / "reference.h5.parts").is_dir():
                break  # mpirun and 2 ranks are up
            time.sleep(0.1)
        assert len(spawned) >= 3 and run.poll() is None, run.communicate()[1][-3000:]
        time.sleep(2.0)  # the ranks are computing
        spawned |= _descendants(run.pid)
        run.send_signal(sig)
        _, err = run.communicate(timeout=120)
    finally:
        if run.poll() is None:
            run.kill()
    assert run.returncode == code, err[-3000:]
    if sig == signal.SIGINT:
        assert err.strip().splitlines()[-1] == INTERRUPTED and "Traceback" not in err, err
        assert err.count(INTERRUPTED) == 1, err
    deadline = time.monotonic() + 60
    while _alive(spawned) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not _alive(spawned), "mpirun or a rank outlived the pipeline"


# ---------------------------------------------------------------------------- fuzzing

KNOWN = {s: [f.name for f in dataclasses.fields(c)] for s, c in SECTIONS.items()}
values = st.recursive(
    st.none() | st.booleans() | st.integers(-10**12, 10**12)
    | st.floats(allow_nan=True, allow_infinity=True) | st.text(max_size=12),
    lambda inner: st.lists(inner, max_size=4), max_leaves=6)
tables = st.dictionaries(st.sampled_from([k for ks in KNOWN.values() for k in ks] + ["x"]),
                         values.filter(lambda v: v is not None), max_size=4)
documents = st.dictionaries(st.sampled_from(list(SECTIONS) + ["name", "junk"]),
                            tables | values.filter(lambda v: v is not None), max_size=5)


@settings(max_examples=150, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(doc=documents, encoding=st.sampled_from(["utf-8", "utf-8", "latin-1", "utf-16"]))
def test_fuzzed_scene_files_are_accepted_or_refused_cleanly(doc, encoding, tmp_path, capsys):
    """Any document: a valid scene, or one SceneError line through the command's failure path
    (a valid one is also priced by the cost estimate, never anything else)."""
    from forcecal.cost import check_cost
    CASES["fuzz examples"] += 1
    path = tmp_path / "fuzz.toml"
    try:
        text = toml_text(doc).encode(encoding)
    except UnicodeEncodeError:
        text = toml_text(doc).encode("utf-8", "surrogatepass")
    path.write_bytes(text)

    def body():
        scene = load_scene(path)
        check_cost(scene, 300, 1500)
        assert scene.name not in (".", "..") and "/" not in scene.name
        assert len(scene.material.prony_g) == 2 and any(scene.gravity.acceleration)
        return 0
    code = run_command(body)
    err = capsys.readouterr().err
    assert "Traceback" not in err and "unexpected" not in err, err
    assert code == 0 or (code == 2 and len(err.strip().splitlines()) == 1
                         and err.startswith("error: ")), err


@settings(max_examples=40, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(n=st.integers(0, 8), tets=st.lists(st.lists(st.integers(-2, 9), min_size=4, max_size=4),
                                          max_size=6),
       coords=st.lists(st.floats(-1e4, 1e4) | st.sampled_from([math.nan, math.inf]),
                       min_size=27, max_size=27),
       scale=st.sampled_from([1e-6, 1e-3, 1.0, 1e3]))
def test_fuzzed_meshes_are_accepted_or_refused_cleanly(n, tets, coords, scale, tmp_path):
    """Random vertices and tets: read_mesh returns a valid mesh or raises MeshError."""
    from forcecal.mesh import read_mesh
    from forcecal.problem import check_organ_scale
    CASES["fuzz examples"] += 1
    points = np.resize(np.asarray(coords, float), (max(n, 1) * 3,)).reshape(-1, 3)[:n]
    cells = np.asarray(tets, dtype=np.int64).reshape(-1, 4)
    path = tmp_path / "fuzz.vtu"
    try:
        meshio.write(path, meshio.Mesh(points if n else np.zeros((0, 3)),
                                       [("tetra", cells)] if len(cells) else []))
    except Exception:  # noqa: BLE001 - meshio cannot even write it: write garbage instead
        path.write_bytes(bytes(range(n * 10)))
    try:
        mesh = read_mesh(path, scale=scale)
        check_organ_scale(mesh, str(path))
    except MeshError:
        pass


def test_a_fixed_rule_selecting_every_vertex_is_refused():
    """Every vertex fixed: refused naming fixed.tolerance (a scipy ValueError before)."""
    from forcecal.point_selection import fixed_nodes
    CASES["table"] += 1
    with pytest.raises(MeshError, match=r"selects all 27 vertices: nothing is left free.*"
                       r"lower fixed.tolerance"):
        fixed_nodes(BOX, "z", "min", 1.0)
