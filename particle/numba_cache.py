"""A kernel from numba's on-disk cache is reused only with the kernel sources it was compiled
from, and wherever those sources are checked out.

numba keys each cached function on its own source file's modification time and size, and
files it under a folder named after the source file's absolute path. Two consequences:

* A kernel that calls kernels of other files compiles them into its own machine code, so
  after one of those files changes (a ``git pull``, an edit) the cached caller still runs
  the old callee, with no warning: numba checks the caller's file only (numba issue #6845,
  open in every release).
* The cache is lost whenever the sources are written anew with the same bytes (a fresh
  clone, a checkout back and forth, a CI cache restored next to a new checkout): every
  kernel compiles again (measured: a first ``make demo`` 3:07 against 2:01 with the caches
  filled; ``tests/test_particle_statics.py`` and ``test_particle_dynamics.py`` 61 s of
  CPU, 58 of them compiling, against 8 s).

Here every cached function whose file lies under a watched folder (the project's,
:data:`PROJECT_ROOT`) is keyed on content instead: its stamp is the SHA-256 of its own
file's bytes and of the kernel package's sources (:func:`sources_digest` of
:data:`KERNEL_PACKAGE`), so any change there makes numba compile every project kernel again
on its next call instead of loading it, and the same bytes anywhere load it. Its cache
folder is named after its folder's path *inside* the watched one (:func:`cache_subpath`),
so checkouts at different paths that share a ``NUMBA_CACHE_DIR`` share their kernels.

What it costs: an edit of a ``particle`` module, a comment included, recompiles every kernel
once; checkouts of *different* sources that share one cache folder replace each other's
entries (each then compiles what the other changed). What it does not change: the machine
code (numba still keys each entry on the CPU it was compiled for), and where the cache
lives (:mod:`forcecal.caches`). :func:`install` runs on import of :mod:`particle`, before
any kernel is decorated (numba reads the stamp then).
"""
from __future__ import annotations

import functools
import hashlib
from pathlib import Path

from numba.core import caching

#: the package whose sources every cached kernel's stamp carries: where the kernels live
KERNEL_PACKAGE = Path(__file__).resolve().parent
#: the folder under which cached functions are keyed on content (the project: the kernels,
#: and the tests' own kernels that call them)
PROJECT_ROOT = KERNEL_PACKAGE.parent

#: watched folder -> the package whose sources key the cached functions under it
_WATCHED: dict[Path, Path] = {}


@functools.lru_cache(maxsize=None)
def sources_digest(package: Path = KERNEL_PACKAGE) -> str:
    """SHA-256 of the names and bytes of the ``*.py`` files of ``package`` (a folder)."""
    digest = hashlib.sha256()
    for path in sorted(Path(package).glob("*.py")):
        digest.update(path.name.encode() + b"\0" + path.read_bytes() + b"\0")
    return digest.hexdigest()


def file_digest(py_file: str | Path) -> str:
    """SHA-256 of the bytes of one source file."""
    return hashlib.sha256(Path(py_file).read_bytes()).hexdigest()


def watch(root: Path, package: Path) -> None:
    """Key the cached functions of files under ``root`` on content, with
    :func:`sources_digest` of ``package`` (from their next decoration on)."""
    _WATCHED[Path(root).resolve()] = Path(package).resolve()


def _watched(py_file: str) -> tuple[Path, Path] | None:
    """(watched root, package whose sources key it) of a cached function's ``py_file``, or
    None when no watched folder holds it."""
    path = Path(py_file).resolve()
    for root, package in _WATCHED.items():
        if path.is_relative_to(root):
            return root, package
    return None


def cache_subpath(py_file: str, root: Path) -> str:
    """The cache folder of the functions of ``py_file`` (a file under the watched ``root``):
    its folder's path relative to ``root`` (``-`` for ``/``; ``project`` for ``root``
    itself) and a hash of that path, the same for every checkout (numba names it after the
    absolute path)."""
    relative = Path(py_file).resolve().parent.relative_to(root).as_posix()
    label = "project" if relative == "." else relative.replace("/", "-")
    return f"{label}_{hashlib.sha1(relative.encode()).hexdigest()}"


def _keyed(source_stamp):
    """numba's source stamp, replaced by the file's and the watched package's digests for a
    watched file."""
    @functools.wraps(source_stamp)
    def get_source_stamp(self):
        watched = _watched(self._py_file)
        if watched is None:
            return source_stamp(self)
        return file_digest(self._py_file), sources_digest(watched[1])
    get_source_stamp.forcecal_keyed = True
    return get_source_stamp


def _relocated(suitable_subpath):
    """numba's cache subfolder, made independent of the checkout's path for a watched file."""
    @functools.wraps(suitable_subpath)
    def get_suitable_cache_subpath(cls, py_file):
        watched = _watched(py_file)
        if watched is None:
            return suitable_subpath.__func__(cls, py_file)
        return cache_subpath(py_file, watched[0])
    get_suitable_cache_subpath.forcecal_keyed = True
    return classmethod(get_suitable_cache_subpath)


def install() -> None:
    """Watch :data:`PROJECT_ROOT` with :data:`KERNEL_PACKAGE`'s sources: key numba's
    source-file cache stamps on content and its cache subfolders on the path inside the
    project (once)."""
    watch(PROJECT_ROOT, KERNEL_PACKAGE)
    mixin = caching._SourceFileBackedLocatorMixin
    if not getattr(mixin.get_source_stamp, "forcecal_keyed", False):
        mixin.get_source_stamp = _keyed(mixin.get_source_stamp)
    locator = caching._CacheLocator
    current = locator.__dict__["get_suitable_cache_subpath"]
    if not getattr(current.__func__, "forcecal_keyed", False):
        locator.get_suitable_cache_subpath = _relocated(current)


install()
