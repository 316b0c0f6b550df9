"""Where numba and FFCx keep their compiled code, settled before either is imported.

numba caches each ``cache=True`` function in ``$NUMBA_CACHE_DIR/<one folder per source
folder>/`` and FFCx (dolfinx's form compiler) in ``$XDG_CACHE_HOME/fenics/``. Both must
*write* there even to reuse what is there (numba replaces its index files, FFCx compiles a
form it has not seen), and both create their folders with the process's umask (755). So
once one user id has filled a shared cache (a container image run under ``--user 12345``,
as clusters run containers), another user id fails at import (numba: ``RuntimeError:
cannot cache function ...: no locator available``) or at its first new form (FFCx).

:func:`settle_caches` checks each configured folder and, when this process cannot write to
it (or to a folder numba made inside it), moves this process to a cache of its own user id
-- ``<the configured folder>/uid-<uid>`` when that folder is writable, else
``<tmp>/forcecal-<tool>-<uid>`` -- and says so in the log. :mod:`forcecal` calls it on
import, so it runs before any project module imports numba or dolfinx.
"""
from __future__ import annotations

import logging
import os
import sys
import tempfile
from pathlib import Path

log = logging.getLogger(__name__)

NUMBA = "NUMBA_CACHE_DIR"
XDG = "XDG_CACHE_HOME"
FFCX_FOLDER = "fenics"  # dolfinx.jit's cache_dir is $XDG_CACHE_HOME/fenics


def _writable(folder: Path) -> bool:
    """This process can create files in ``folder`` (an existing directory)."""
    return os.access(folder, os.W_OK | os.X_OK)


def folder_is_usable(folder: Path, subfolders: bool = False) -> bool:
    """Whether this process can keep a cache in ``folder``.

    ``folder`` must be a directory this process can write to, or one it can create; with
    ``subfolders`` every folder already inside it (numba's per-source folders; not the
    ``uid-*`` ones of other users) must be writable too.
    """
    if not folder.exists():
        parent = next((p for p in folder.parents if p.exists()), None)
        return parent is not None and parent.is_dir() and _writable(parent)
    if not folder.is_dir() or not _writable(folder):
        return False
    if not subfolders:
        return True
    try:
        return all(_writable(Path(entry.path)) for entry in os.scandir(folder)
                   if entry.is_dir() and not entry.name.startswith("uid-"))
    except OSError:
        return False


def per_uid_folder(shared: Path, tool: str, uid: int) -> Path:
    """The cache folder of user ``uid`` when the ``shared`` one is not usable."""
    if shared.is_dir() and _writable(shared):
        return shared / f"uid-{uid}"
    return Path(tempfile.gettempdir()) / f"forcecal-{tool}-{uid}"


def settle_caches(environ=os.environ) -> dict[str, Path]:
    """Point numba and FFCx at cache folders this process can use.

    Returns ``{variable: new value}`` for each variable it changed. A variable that is not
    set is left to the tool's default (numba and FFCx then use the home folder).
    """
    uid = os.getuid()
    moved: dict[str, Path] = {}
    if environ.get(NUMBA) and not folder_is_usable(Path(environ[NUMBA]), subfolders=True):
        moved[NUMBA] = per_uid_folder(Path(environ[NUMBA]), "numba", uid)
        config = sys.modules.get("numba.core.config")
        if config is not None:  # numba already imported: it read the variable then
            config.CACHE_DIR = str(moved[NUMBA])
    if environ.get(XDG) and not folder_is_usable(Path(environ[XDG]) / FFCX_FOLDER):
        moved[XDG] = per_uid_folder(Path(environ[XDG]), "ffcx", uid)
    for variable, folder in moved.items():
        log.info("cache %s=%s is not writable by uid %d (another user filled it); using %s",
                 variable, environ[variable], uid, folder)
        environ[variable] = str(folder)
    return moved
