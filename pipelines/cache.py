"""Content-addressed stage cache: a stage reruns only when something it reads has changed.

A stage's *inputs* are recorded as fingerprints (:class:`StageInputs`):

* ``scene``: ``Scene.fingerprint(section)`` of every scene section the stage reads;
* ``mesh``: the mesh fingerprint (only for the stage that reads the mesh itself,
  the FE reference; later stages read the mesh back from ``reference.h5``);
* ``upstream``: SHA-256 of the content of every upstream file it reads;
* ``code``: a digest of every project source file the stage's entry modules
  import, transitively (:func:`import_closure`), so editing a module the
  stage does not use does not invalidate it; comments, formatting and
  docstrings are left out (:func:`source_digest`).

After a successful run :meth:`Cache.store` writes ``<out>/cache/<stage>.json``
with those inputs and the content hash of every output file. :meth:`Cache.check`
compares the current inputs and outputs with that record and returns the list
of reasons to rerun (empty = up to date), e.g. ``["scene [material] changed",
"output params.h5 is missing"]``. Outputs are hashed too, so a file deleted or
replaced by hand is noticed.
"""

from __future__ import annotations

import ast
import hashlib
import importlib.util
import json
import logging
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from forcecal import PROJECT_PACKAGES
from forcecal.errors import DataFileError
from forcecal.h5io import atomic_path
from forcecal.provenance import file_digest

log = logging.getLogger(__name__)

RECORD_VERSION = 3


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


def _imported_names(path: Path) -> set[str]:
    """Dotted names a source file imports anywhere (top level or inside functions)."""
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            names.add(node.module)
            names.update(f"{node.module}.{a.name}" for a in node.names)  # maybe submodules
    return names


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


def source_digest(path: Path) -> str:
    """SHA-256 of a module's syntax tree without docstrings.

    Comments, formatting and docstrings do not change what a stage computes, so
    editing them must not force a rerun; every other change (code, string
    constants such as messages) does.
    """
    tree = ast.parse(path.read_text(), str(path))
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if (isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef))
                and body and isinstance(body[0], ast.Expr)
                and isinstance(body[0].value, ast.Constant)
                and isinstance(body[0].value.value, str)):
            node.body = body[1:] or [ast.Pass()]
    return hashlib.sha256(ast.dump(tree).encode()).hexdigest()


def code_digests(entries: tuple[str, ...]) -> dict[str, str]:
    """``{file path relative to its package root: source_digest}`` of the import closure."""
    closure = import_closure(entries)
    out = {}
    for name, path in closure.items():
        rel = path.relative_to(package_root(name.split(".")[0]))
        out[str(rel)] = source_digest(path)
    return dict(sorted(out.items()))


def code_digest(*entries: str) -> str:
    """One SHA-256 over :func:`code_digests` of ``entries`` (e.g. ``code_digest("reference_fe")``)."""
    return hashlib.sha256(json.dumps(code_digests(entries), sort_keys=True).encode()).hexdigest()


@dataclass(frozen=True)
class StageInputs:
    """Fingerprints of everything a stage reads (see module docstring)."""
    scene: dict[str, str] = field(default_factory=dict)
    mesh: str | None = None
    upstream: dict[str, str] = field(default_factory=dict)
    code: dict[str, str] = field(default_factory=dict)

    def changes_from(self, old: dict[str, Any]) -> list[str]:
        """Human-readable differences between these inputs and a stored record's ``old``."""
        reasons = [f"scene [{k}] changed" for k in sorted(self.scene)
                   if old.get("scene", {}).get(k) != self.scene[k]]
        if self.mesh != old.get("mesh"):
            reasons.append("mesh changed")
        reasons += [f"{k} changed" for k in sorted(self.upstream)
                    if old.get("upstream", {}).get(k) != self.upstream[k]]
        old_code = old.get("code", {})
        changed = sorted(set(self.code) ^ set(old_code)
                         | {k for k in self.code if old_code.get(k) != self.code[k]})
        if changed:
            shown = ", ".join(changed[:5]) + (f" and {len(changed) - 5} more"
                                              if len(changed) > 5 else "")
            reasons.append(f"code changed: {shown}")
        return reasons


class Cache:
    """The cache records of one output folder (``<out>/cache/<stage>.json``)."""

    def __init__(self, out: str | Path) -> None:
        self.out = Path(out)
        self.folder = self.out / "cache"

    def record_path(self, stage: str) -> Path:
        return self.folder / f"{stage}.json"

    def load(self, stage: str) -> dict[str, Any] | None:
        """The stored record of ``stage``, or None if there is none (or it is unreadable)."""
        path = self.record_path(stage)
        if not path.is_file():
            return None
        try:
            record = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            log.warning("ignoring unreadable cache record %s: %s", path, exc)
            return None
        return record if record.get("version") == RECORD_VERSION else None

    def check(self, stage: str, inputs: StageInputs) -> list[str]:
        """Reasons why ``stage`` must run (empty list = its recorded outputs are up to date)."""
        record = self.load(stage)
        if record is None:
            return ["no cache record"]
        reasons = inputs.changes_from(record.get("inputs", {}))
        for name, digest in record.get("outputs", {}).items():
            path = self.out / name
            if not path.is_file():
                reasons.append(f"output {name} is missing")
            elif digest != file_digest(path):
                reasons.append(f"output {name} was modified")
        return reasons

    def store(self, stage: str, inputs: StageInputs, outputs: list[str], elapsed: float,
              note: str = "") -> None:
        """Record a successful run of ``stage`` (written atomically)."""
        record = {"version": RECORD_VERSION, "stage": stage, "inputs": asdict(inputs),
                  "outputs": {n: file_digest(self.out / n) for n in outputs},
                  "elapsed_s": elapsed, "finished": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
                  "note": note}
        with atomic_path(self.record_path(stage)) as tmp:
            tmp.write_text(json.dumps(record, indent=1, sort_keys=True))

    def elapsed(self, stage: str) -> float | None:
        """Wall time [s] of the recorded run of ``stage``, if any."""
        record = self.load(stage)
        return None if record is None else record.get("elapsed_s")
