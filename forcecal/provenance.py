"""Where results come from: content digests of files and the git commit of the checkout.

Shared by the calibration (its checkpoint key, ``params.h5`` versions) and the
pipelines (stage cache keys, ``report.json``, ``bench.json``).
"""
from __future__ import annotations

import hashlib
import importlib.util
import os
import subprocess
from pathlib import Path

from forcecal.errors import DataFileError

#: the checkout (or site-packages folder) holding the project's packages
ROOT = Path(__file__).resolve().parents[1]
CHUNK = 1 << 20


def file_digest(path: str | Path) -> str:
    """SHA-256 of a file's bytes (hex); DataFileError if it cannot be read."""
    h = hashlib.sha256()
    try:
        with open(path, "rb") as fh:
            while chunk := fh.read(CHUNK):
                h.update(chunk)
    except OSError as exc:
        raise DataFileError(f"cannot read {path} to fingerprint it: {exc}") from exc
    return h.hexdigest()


def packages_digest(packages: tuple[str, ...]) -> str:
    """SHA-256 over the path and bytes of every ``.py`` file of ``packages`` (found unimported).

    Byte-exact and so conservative: a comment edit also counts as a change (what is keyed
    on it is then recomputed, which costs a rerun, never a wrong result).
    """
    h = hashlib.sha256()
    for package in packages:
        folder = Path(next(iter(importlib.util.find_spec(package).submodule_search_locations)))
        for path in sorted(folder.rglob("*.py")):
            h.update(f"{package}/{path.relative_to(folder)}".encode() + b"\0"
                     + path.read_bytes() + b"\0")
    return h.hexdigest()


def git_commit(root: str | Path = ROOT) -> str | None:
    """``git rev-parse HEAD`` of the checkout holding ``root`` (``+dirty`` if tracked files
    differ from it); None outside a git checkout or without git. For the project itself
    without its ``.git`` (the container image), the commit recorded at build time in
    ``FORCECAL_GIT_COMMIT`` (the Dockerfile's ``GIT_COMMIT`` build argument), if any."""
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True,
                              text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "diff", "--quiet", "HEAD", "--"], cwd=root,
                               capture_output=True).returncode
    except (OSError, subprocess.CalledProcessError):
        recorded = os.environ.get("FORCECAL_GIT_COMMIT", "").strip()
        return recorded if recorded and Path(root).resolve() == ROOT.resolve() else None
    return head + ("+dirty" if dirty else "")
