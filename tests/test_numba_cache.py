"""particle.numba_cache: a cached kernel is not reused after a kernel it calls changed.

numba 0.56 keys a cached function on its own file's modification time and size only, so a
caller whose file did not change keeps running an edited callee's old code from its cache.
The end-to-end test builds that case (a caller and a callee in two files, the callee edited
between two processes sharing one cache folder) and runs it without and with the watch."""
import os
import subprocess
import sys
import textwrap
from pathlib import Path

from particle import kernels, numba_cache

ROOT = Path(__file__).resolve().parents[1]

CALLER = """\
from numba import njit
from kpkg.callee import value


@njit(cache=True)
def run():
    return value() + 0.0
"""

SCRIPT = """\
import sys
from pathlib import Path
import particle.numba_cache as numba_cache
if sys.argv[1] == "watch":
    folder = Path(sys.argv[2])
    numba_cache.watch(folder, folder / "kpkg")
from kpkg.caller import run
print(run())
"""


def test_a_project_kernels_stamp_carries_the_kernel_sources_digest():
    """The stamp numba stores with (and checks against) a cached kernel's index ends with the
    digest of the particle package's sources; the digest follows the files' bytes."""
    stamp = kernels.add_connector_forces._cache._cache_file._source_stamp
    assert stamp[-1] == numba_cache.sources_digest() and len(stamp) == 3
    assert numba_cache.sources_digest.__wrapped__(numba_cache.KERNEL_PACKAGE) == stamp[-1]


def test_digest_changes_with_any_source_byte(tmp_path):
    (tmp_path / "a.py").write_text("x = 1\n")
    (tmp_path / "b.py").write_text("y = 2\n")
    before = numba_cache.sources_digest.__wrapped__(tmp_path)
    (tmp_path / "b.py").write_text("y = 3\n")
    assert numba_cache.sources_digest.__wrapped__(tmp_path) != before


def _run(folder: Path, cache: Path, mode: str) -> float:
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache),
               PYTHONPATH=os.pathsep.join([str(folder), str(ROOT)]))
    out = subprocess.run([sys.executable, "-c", SCRIPT, mode, str(folder)], env=env,
                         capture_output=True, text=True, timeout=120, check=True)
    return float(out.stdout.split()[-1])


def _package(folder: Path) -> None:
    (folder / "kpkg").mkdir(parents=True)
    (folder / "kpkg" / "__init__.py").write_text("")
    (folder / "kpkg" / "caller.py").write_text(CALLER)
    _callee(folder, 1.0)


def _callee(folder: Path, value: float) -> None:
    (folder / "kpkg" / "callee.py").write_text(textwrap.dedent(f"""\
        from numba import njit


        @njit(cache=True)
        def value():
            return {value!r}
        """))


def test_an_edited_callee_is_not_run_from_a_stale_cached_caller(tmp_path):
    """Without the watch the second process runs the callee's old value from the caller's
    cache (numba's own behaviour, what the module guards against); with it, the new one."""
    for mode, expected in (("plain", 1.0), ("watch", 2.0)):
        folder, cache = tmp_path / mode, tmp_path / mode / "cache"
        _package(folder)
        assert _run(folder, cache, mode) == 1.0
        _callee(folder, 2.0)
        assert _run(folder, cache, mode) == expected, mode
