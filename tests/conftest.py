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

# `make test` runs two pytest workers side by side (pytest-xdist). FFCx's JIT cache lets a
# process wait only 10 s for a form that another process is compiling, then raises
# TimeoutError; its MPI ranks share one compile, separate processes do not. So each worker
# gets a JIT cache of its own (set before anything imports dolfinx, which reads it once;
# mpirun and subprocesses inherit it).
if "PYTEST_XDIST_WORKER" in os.environ:
    _cache = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache"))
    os.environ["XDG_CACHE_HOME"] = str(_cache / f"pytest-{os.environ['PYTEST_XDIST_WORKER']}")


# The test files that take longest, longest first (per-file time of `pytest --durations=0 -n 2
# --dist loadfile` on a cold cache, 10 s and up; refresh when a file's cost moves). `make test`
# hands whole files to two workers in collection order, so a long file collected late leaves
# one core idle at the end while the other finishes it: these run first and the short files
# fill in behind them (longest-processing-time-first). A file's tests keep their order, so its
# module fixtures are still computed once; files not listed follow in their usual order.
LONGEST_FILES = (
    "test_calibration_gradient.py", "test_pipeline_e2e.py", "test_calibration_fit.py",
    "test_validation_failures.py", "test_fe_point_failures.py", "test_examples.py",
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
