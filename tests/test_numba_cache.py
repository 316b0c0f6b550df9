"""particle.numba_cache: a cached kernel is not reused after a kernel it calls changed, and is
reused by any checkout of the same sources.

numba 0.56 keys a cached function on its own file's modification time and size only, so a
caller whose file did not change keeps running an edited callee's old code from its cache,
and files it under a folder named after the file's absolute path, so the same bytes at
another path or written again compile again. The end-to-end tests build those cases (a
caller and a callee in two files, run by processes sharing one cache folder) and run them
without and with the watch."""
import hashlib
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
value = run()
print(sum(run.stats.cache_hits.values()), value)
"""


def test_a_project_kernels_stamp_is_its_files_and_the_kernel_sources_digests():
    """The stamp numba stores with (and checks against) a cached kernel's index is the digest
    of its own file and of the particle package's sources (no modification time); the
    digests follow the files' bytes. Its cache folder is named after its folder inside the
    project, not after the checkout's path."""
    cache = kernels.add_connector_forces._cache
    stamp = cache._cache_file._source_stamp
    assert stamp == (numba_cache.file_digest(kernels.__file__), numba_cache.sources_digest())
    assert numba_cache.sources_digest.__wrapped__(numba_cache.KERNEL_PACKAGE) == stamp[-1]
    folder = Path(cache._cache_path).name
    assert folder == numba_cache.cache_subpath(kernels.__file__, ROOT)
    assert folder == "particle_" + hashlib.sha1(b"particle").hexdigest()


def test_digest_changes_with_any_source_byte(tmp_path):
    (tmp_path / "a.py").write_text("x = 1\n")
    (tmp_path / "b.py").write_text("y = 2\n")
    before = numba_cache.sources_digest.__wrapped__(tmp_path)
    (tmp_path / "b.py").write_text("y = 3\n")
    assert numba_cache.sources_digest.__wrapped__(tmp_path) != before


def _run(folder: Path, cache: Path, mode: str) -> tuple[int, float]:
    """(cache hits, value) of the caller run in a fresh process: ``mode`` "watch" keys the
    package's kernels on content, "plain" leaves numba's own keys."""
    # no bytecode files for the test's package: Python reuses a module's .pyc while the source's
    # modification time (whole seconds) and size match it, so a callee edited within the second
    # its first run started (same size: 1.0 -> 2.0) would run its old value whatever numba does
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache), PYTHONDONTWRITEBYTECODE="1",
               PYTHONPATH=os.pathsep.join([str(folder), str(ROOT)]))
    out = subprocess.run([sys.executable, "-c", SCRIPT, mode, str(folder)], env=env,
                         capture_output=True, text=True, timeout=120, check=True)
    hits, value = out.stdout.split()[-2:]
    return int(hits), float(value)


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
        assert _run(folder, cache, mode)[1] == 1.0
        _callee(folder, 2.0)
        assert _run(folder, cache, mode)[1] == expected, mode


def test_the_same_sources_anywhere_load_the_cached_kernel(tmp_path):
    """Two checkouts of the same bytes at two paths, sharing one cache folder, and the same
    bytes written again (a new modification time): with the watch the second checkout and
    the rewritten one load the caller from the cache (a cache hit, no compile); numba's own
    keys compile it again in both cases."""
    for mode, hits in (("plain", 0), ("watch", 1)):
        cache = tmp_path / mode / "cache"
        first, second = tmp_path / mode / "first", tmp_path / mode / "second"
        _package(first)
        _package(second)
        assert _run(first, cache, mode) == (0, 1.0)  # compiled and written
        assert _run(second, cache, mode) == (hits, 1.0), mode
        caller = first / "kpkg" / "caller.py"
        caller.write_bytes(caller.read_bytes())
        stat = caller.stat()
        os.utime(caller, ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))
        assert _run(first, cache, mode) == (hits, 1.0), mode
