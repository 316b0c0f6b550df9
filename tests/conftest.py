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
