"""A kernel from numba's on-disk cache is reused only with the kernel sources it was compiled from.

numba keys each cached function on its own source file's modification time and size. A
kernel that calls kernels of other files compiles them into its own machine code, so after
one of those files changes (a ``git pull``, an edit) the cached caller still runs the old
callee, with no warning: numba checks the caller's file only (numba issue #6845, open in
every release). Here the stamp of every cached function whose file lies under a watched
folder (the project's, :data:`PROJECT_ROOT`) also carries a digest of the kernel package's
sources (:func:`sources_digest` of :data:`KERNEL_PACKAGE`), so any change there makes numba
compile every project kernel again on its next call instead of loading it.

What it costs: an edit of a ``particle`` module, a comment included, recompiles every kernel
once (a fresh cache, as a new clone has). What it does not change: the machine code, and
where the cache lives (:mod:`forcecal.caches`). :func:`install` runs on import of
:mod:`particle`, before any kernel is decorated (numba reads the stamp then).
"""
from __future__ import annotations

import functools
import hashlib
from pathlib import Path

from numba.core import caching

#: the package whose sources every cached kernel's stamp carries: where the kernels live
KERNEL_PACKAGE = Path(__file__).resolve().parent
#: the folder under which cached functions are stamped with it (the project: the kernels,
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


def watch(root: Path, package: Path) -> None:
    """Stamp the cached functions of files under ``root`` with :func:`sources_digest` of
    ``package`` too (from their next decoration on)."""
    _WATCHED[Path(root).resolve()] = Path(package).resolve()


def _package_of(py_file: str) -> Path | None:
    """The watched package whose sources key a cached function of ``py_file``, or None."""
    path = Path(py_file).resolve()
    for root, package in _WATCHED.items():
        if path.is_relative_to(root):
            return package
    return None


def _keyed(source_stamp):
    """numba's source stamp, with the digest of the watched package for a watched file."""
    @functools.wraps(source_stamp)
    def get_source_stamp(self):
        stamp = source_stamp(self)
        package = _package_of(self._py_file)
        return stamp if package is None else (*stamp, sources_digest(package))
    get_source_stamp.forcecal_keyed = True
    return get_source_stamp


def install() -> None:
    """Watch :data:`PROJECT_ROOT` with :data:`KERNEL_PACKAGE`'s sources and key numba's
    source-file cache stamps on them (once)."""
    watch(PROJECT_ROOT, KERNEL_PACKAGE)
    mixin = caching._SourceFileBackedLocatorMixin
    if not getattr(mixin.get_source_stamp, "forcecal_keyed", False):
        mixin.get_source_stamp = _keyed(mixin.get_source_stamp)


install()
