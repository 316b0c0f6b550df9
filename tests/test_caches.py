"""The numba and FFCx cache folders: a shared cache another user id filled breaks no import."""
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from forcecal.caches import NUMBA, XDG, folder_is_usable, per_uid_folder, settle_caches

ROOT = Path(__file__).resolve().parents[1]
NOBODY = 65534


def test_usable_folders(tmp_path):
    assert folder_is_usable(tmp_path)
    assert folder_is_usable(tmp_path / "not" / "yet")  # created by numba under a writable parent
    (tmp_path / "file").write_text("")
    assert not folder_is_usable(tmp_path / "file")      # a file is no cache folder


def test_per_uid_folder(tmp_path):
    assert per_uid_folder(tmp_path, "numba", 12345) == tmp_path / "uid-12345"
    missing = tmp_path / "missing"
    assert per_uid_folder(missing, "ffcx", 7) == Path(tempfile.gettempdir()) / "forcecal-ffcx-7"


def test_unset_variables_are_left_to_the_tools():
    environ = {}
    assert settle_caches(environ) == {}
    assert environ == {}


def test_usable_folders_are_kept(tmp_path):
    environ = {NUMBA: str(tmp_path / "numba"), XDG: str(tmp_path)}
    assert settle_caches(environ) == {}
    assert environ == {NUMBA: str(tmp_path / "numba"), XDG: str(tmp_path)}


def _as_nobody():
    os.setgroups([])
    os.setgid(NOBODY)
    os.setuid(NOBODY)


@pytest.mark.skipif(not hasattr(os, "getuid") or os.getuid() != 0,
                    reason="needs root to run a process as another user id")
def test_cache_filled_by_another_uid(tmp_path):
    """The container case: root fills the caches (folders 755), uid 65534 imports the kernels.

    Without the per-uid fallback numba raises ``cannot cache function ...: no locator
    available`` at import, and FFCx could not compile a form into root's folder.
    """
    shared = Path(tempfile.mkdtemp(prefix="forcecal-numba-test-", dir="/tmp"))
    try:
        shared.chmod(0o755)
        cache = shared / "numba"
        (shared / "fenics").mkdir(mode=0o755)  # as FFCx leaves it
        env = dict(os.environ, PYTHONPATH=str(ROOT), HOME=str(shared),
                   **{NUMBA: str(cache), XDG: str(shared)})
        code = ("import particle.volume, os; "
                "print(os.environ['NUMBA_CACHE_DIR'], os.environ['XDG_CACHE_HOME'])")
        filled = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                                text=True)
        assert filled.returncode == 0, filled.stderr
        assert any(p.is_dir() for p in cache.iterdir())  # numba made its source folder(s)
        probe = subprocess.run([sys.executable, "-c", "import forcecal"], env=env,
                               preexec_fn=_as_nobody, capture_output=True, text=True)
        if probe.returncode != 0:
            pytest.skip(f"the project is not readable by uid {NOBODY}: {probe.stderr[-200:]}")
        other = subprocess.run([sys.executable, "-c", code], env=env, preexec_fn=_as_nobody,
                               capture_output=True, text=True)
        assert other.returncode == 0, other.stderr
        tmp = Path(tempfile.gettempdir())
        assert other.stdout.split() == [str(tmp / f"forcecal-numba-{NOBODY}"),
                                        str(tmp / f"forcecal-ffcx-{NOBODY}")]
    finally:
        subprocess.run(["rm", "-rf", str(shared), *(str(Path(tempfile.gettempdir())
                                                        / f"forcecal-{tool}-{NOBODY}")
                                                    for tool in ("numba", "ffcx"))])
