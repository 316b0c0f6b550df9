"""Where results come from, and whether what produced them has changed: fingerprints.

One way to decide "did this change?" for every cache and checkpoint of the
project (the pipeline's stage cache, the calibration checkpoint, the FE work
items and stored experiments, the benchmarks):

* **file fingerprint** (:func:`file_digest`): SHA-256 of a file's bytes;
* **section fingerprint** (:func:`section_fingerprint`): SHA-256 of scene
  sections as sorted JSON (:func:`json_digest` of any JSON-able value);
* **code fingerprint** (:func:`code_digests`, :func:`code_digest`): the syntax
  tree, without docstrings, of every project module some entry modules import,
  transitively (:func:`import_closure`). Editing a module they do not import,
  or a comment, the formatting or a docstring, leaves it unchanged: those
  cannot change a result.

Plus :func:`git_commit`, the commit recorded in every result. Nothing here
imports the packages it fingerprints (sources are read with :mod:`ast`), so
the pipeline can fingerprint the FE code without importing dolfinx.
"""
from __future__ import annotations

import ast
import functools
import hashlib
import importlib.util
import json
import os
import subprocess
from pathlib import Path
from typing import Any

from forcecal import PROJECT_PACKAGES
from forcecal.errors import DataFileError

#: the checkout (or site-packages folder) holding the project's packages
ROOT = Path(__file__).resolve().parents[1]
CHUNK = 1 << 20


# ---------------------------------------------------------------------------- files and values

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


def json_digest(value: Any) -> str:
    """SHA-256 of ``value`` as JSON with sorted keys (tuples and arrays as lists)."""
    return hashlib.sha256(json.dumps(value, sort_keys=True, default=list).encode()).hexdigest()


def section_fingerprint(scene: Any, *sections: str) -> str:
    """SHA-256 of the named sections of ``scene`` (a :class:`forcecal.scene.Scene`), each as
    its dict of values: equal whenever every value the sections hold is equal."""
    return json_digest({s: scene.section_dict(s) for s in sections})


# ---------------------------------------------------------------------------- code

def package_root(package: str) -> Path:
    """Folder holding the top-level ``package`` (found without importing it)."""
    spec = importlib.util.find_spec(package)
    if spec is None or not spec.submodule_search_locations:
        raise DataFileError(f"cannot fingerprint the code of {package!r}: it is not an "
                            "importable package")
    return Path(next(iter(spec.submodule_search_locations))).parent


def module_file(name: str, roots: dict[str, Path]) -> Path | None:
    """Source file of dotted module ``name`` if it lies in one of the packages of ``roots``."""
    top = name.split(".")[0]
    if top not in roots:
        return None
    base = roots[top].joinpath(*name.split("."))
    for candidate in (base.with_suffix(".py"), base / "__init__.py"):
        if candidate.is_file():
            return candidate
    return None


def _imported_names(path: Path) -> frozenset[str]:
    """Dotted names a source file imports anywhere (top level or inside functions)."""
    return _names_imported_by(path.read_text(), str(path))


@functools.lru_cache(maxsize=1024)
def _names_imported_by(source: str, filename: str) -> frozenset[str]:
    names: set[str] = set()
    for node in ast.walk(ast.parse(source, filename)):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            names.add(node.module)
            names.update(f"{node.module}.{a.name}" for a in node.names)  # maybe submodules
    return frozenset(names)


def import_closure(entries: tuple[str, ...]) -> dict[str, Path]:
    """Every project module the ``entries`` import, transitively: ``{module name: file}``.

    An entry is a module, or a package standing for all of its modules.
    Imports are read from the source (:mod:`ast`), so nothing is imported and
    lazy imports inside functions count too. Only modules of the project's
    packages (and of the entries' own top-level packages) are followed; each
    module brings the ``__init__`` of its parent packages, which Python runs
    on import.
    """
    roots = {p: package_root(p) for p in {e.split(".")[0] for e in entries}}
    roots.update({p: package_root(p) for p in PROJECT_PACKAGES
                  if p not in roots and importlib.util.find_spec(p) is not None})
    pending = []
    for entry in entries:
        path = module_file(entry, roots)
        if path is None:
            raise DataFileError(f"cannot fingerprint the code of {entry!r}: no source file")
        pending.append(entry)
        if path.name == "__init__.py":  # a package entry: all of its modules
            pending += [".".join((entry, *f.relative_to(path.parent).with_suffix("").parts))
                        for f in sorted(path.parent.rglob("*.py"))
                        if f.name != "__init__.py" and "__pycache__" not in f.parts]
    found: dict[str, Path] = {}
    while pending:
        name = pending.pop()
        path = module_file(name, roots)
        if name in found or path is None:
            continue
        found[name] = path
        parts = name.split(".")
        pending += [".".join(parts[:k]) for k in range(1, len(parts))]
        pending += sorted(_imported_names(path))
    return found


def source_digest(path: Path, ignored_classes: frozenset[str] = frozenset()) -> str:
    """SHA-256 of a module's syntax tree without docstrings.

    Comments, formatting and docstrings do not change what the code computes,
    so editing them must not discard a result; every other change (code,
    string constants such as messages) does. ``ignored_classes``: names of
    top-level classes left out as well (the scene sections a computation does
    not read, :func:`code_digests`).
    """
    return _tree_digest(path.read_text(), str(path), ignored_classes)


@functools.lru_cache(maxsize=1024)  # keyed on the text: the stages share most of their modules
def _tree_digest(source: str, filename: str, ignored_classes: frozenset[str] = frozenset()
                 ) -> str:
    tree = ast.parse(source, filename)
    if ignored_classes:
        tree.body = [node for node in tree.body
                     if not (isinstance(node, ast.ClassDef) and node.name in ignored_classes)]
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if (isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef))
                and body and isinstance(body[0], ast.Expr)
                and isinstance(body[0].value, ast.Constant)
                and isinstance(body[0].value.value, str)):
            node.body = body[1:] or [ast.Pass()]
    return hashlib.sha256(ast.dump(tree).encode()).hexdigest()


def code_digests(entries: tuple[str, ...],
                 ignored: dict[str, frozenset[str]] | None = None) -> dict[str, str]:
    """``{file path relative to its package root: source_digest}`` of the import closure of
    ``entries`` (per file, so a cache can say which files changed).

    ``ignored``: ``{module name: top-level class names}`` left out of those modules' digests,
    e.g. the FE reference's ``{"forcecal.scene": {"CalibrationSection", ...}}``: the sections
    a computation does not read are defined in the module that loads every scene, but neither
    their code nor their values (left out of the section fingerprint too) change its result,
    so a new calibration key does not make an FE reference stale.
    """
    closure = import_closure(entries)
    ignored = ignored or {}
    out = {}
    for name, path in closure.items():
        rel = path.relative_to(package_root(name.split(".")[0]))
        out[str(rel)] = source_digest(path, frozenset(ignored.get(name, ())))
    return dict(sorted(out.items()))


def code_digest(*entries: str, ignored: dict[str, frozenset[str]] | None = None) -> str:
    """The code fingerprint of ``entries`` in one SHA-256 (over :func:`code_digests`), e.g.
    ``code_digest("reference_fe.run")``."""
    return hashlib.sha256(json.dumps(code_digests(entries, ignored),
                                     sort_keys=True).encode()).hexdigest()


# ---------------------------------------------------------------------------- checkout

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
