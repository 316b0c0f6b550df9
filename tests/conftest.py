import json
import logging
import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCENES = ROOT / "scenes"

os.environ.setdefault("OMPI_ALLOW_RUN_AS_ROOT", "1")
os.environ.setdefault("OMPI_ALLOW_RUN_AS_ROOT_CONFIRM", "1")
# numba's OpenMP threading layer (the multi-threaded step's tests use two threads) spins
# idle threads by default: with two pytest workers on two cores a spinning thread takes the
# other worker's core, and its barrier waits for a core. Measured on test_particle_threads +
# the threaded volume tests (warm cache, -n 0, loaded machine): 6.8 -> 1.3 s CPU, 17.8 ->
# 3.8 s wall. Set before numba loads libgomp (which reads it once); the results do not
# depend on it (the blocks' forces are summed in block order).
os.environ.setdefault("OMP_WAIT_POLICY", "passive")

# `make test` runs two pytest workers side by side (pytest-xdist) that share one FFCx JIT
# cache, so a form is compiled once per session rather than once per worker (~35 s of CPU on
# a cold cache). A process that finds a form another process is compiling waits for it, by
# default for 10 s (dolfinx's JIT parameter "timeout"), then raises TimeoutError: a P2 form
# compiled on a loaded machine can take longer. The tests' processes wait up to
# JIT_WAIT_S, from a dolfinx JIT parameters file in a config folder of the test session's own
# (dolfinx reads $XDG_CONFIG_HOME/dolfinx/dolfinx_jit_parameters.json once, at its first
# JIT; mpirun and subprocesses inherit the variable).
JIT_WAIT_S = 120
_config = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "pytest-config"
_parameters = _config / "dolfinx" / "dolfinx_jit_parameters.json"
_text = json.dumps({"timeout": JIT_WAIT_S})
if not _parameters.exists() or _parameters.read_text() != _text:
    _parameters.parent.mkdir(parents=True, exist_ok=True)
    _partial = _parameters.with_suffix(f".{os.getpid()}")
    _partial.write_text(_text)
    os.replace(_partial, _parameters)  # atomic: another process never reads half a file
os.environ["XDG_CONFIG_HOME"] = str(_config)


def pytest_sessionstart(session):
    """Before the workers start: remove the C files of FFCx compiles that never finished
    (a process killed while compiling leaves its ``.c`` without the ``.c.cached`` that
    says it is ready), on which every later process would wait :data:`JIT_WAIT_S` and fail."""
    if "PYTEST_XDIST_WORKER" in os.environ:
        return
    cache = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "fenics"
    for source in cache.glob("libffcx_*.c"):
        if not source.with_suffix(".c.cached").exists():
            source.unlink(missing_ok=True)


# The test files that take longest, longest first (per-file time of `pytest --durations=0 -n 2
# --dist loadfile` on a cold cache, 10 s and up; refresh when a file's cost moves). `make test`
# hands whole files to two workers in collection order, so a long file collected late leaves
# one core idle at the end while the other finishes it: these run first and the short files
# fill in behind them (longest-processing-time-first). A file's tests keep their order, so its
# module fixtures are still computed once; files not listed follow in their usual order.
# One exception to longest-first: the FE-only test_fe_point_failures goes second, ahead of the
# pipeline files, so the other worker's first calibration starts after test_calibration_gradient
# has compiled the static Newton loop into the numba cache (~15 s of CPU); started together,
# both processes compiled it (and a calibration's worker processes, each).
LONGEST_FILES = (
    "test_calibration_gradient.py", "test_fe_point_failures.py", "test_pipeline_e2e.py",
    "test_calibration_fit.py", "test_validation_failures.py", "test_examples.py",
    "test_user_mesh.py", "test_body.py", "test_fe_physics.py", "test_fe_floor.py",
    "test_faults.py", "test_fe_reference.py", "test_particle_volume.py", "test_experiments.py",
    "test_calibration_volume.py", "test_bench.py", "test_volume_regression.py",
    "test_fe_punch.py", "test_study_fold_cv.py", "test_calibration_inputs.py", "test_corpus.py",
    "test_particle_threads.py", "test_haptic_volume.py", "test_bad_input.py",
    "test_fe_sensitivity.py",
)


def pytest_collection_modifyitems(items):
    """Run the :data:`LONGEST_FILES` first, longest first (a stable sort: the order within a
    file and of the other files is kept)."""
    rank = {name: i for i, name in enumerate(LONGEST_FILES)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))


@pytest.fixture(scope="session")
def liver_scene():
    from forcecal.scene import load_scene
    return load_scene(SCENES / "liver.toml")


@pytest.fixture(scope="session")
def liver_problem(liver_scene):
    from forcecal.problem import build_problem
    return build_problem(liver_scene)


@pytest.fixture(autouse=True)
def _quiet_logs(caplog):
    caplog.set_level(logging.WARNING)


@pytest.fixture(autouse=True)
def _restore_root_handlers():
    """A command line run in-process (``configure_logging``) replaces the root logger's
    handlers with one bound to that test's captured stderr; put the previous ones back, so
    a later test's records never go to a stream pytest has closed."""
    handlers, level = list(logging.root.handlers), logging.root.level
    yield
    logging.root.handlers[:] = handlers
    logging.root.setLevel(level)
