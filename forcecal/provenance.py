"""Where results come from, and whether what produced them has changed: fingerprints.

One way to decide "did this change?" for every cache and checkpoint of the
project (the pipeline's stage cache, the calibration checkpoint, the FE work
items and stored experiments, the benchmarks):

* **file fingerprint** (:func:`file_digest`): SHA-256 of a file's bytes;
* **section fingerprint** (:func:`section_fingerprint`): SHA-256 of scene
  sections as sorted JSON (:func:`json_digest` of any JSON-able value);
* **code fingerprint** (:class:`CodeDependencies`): the syntax tree, without
  docstrings, of the modules a computation declares it depends on; every
  cached computation's declaration is here (:data:`FE`, :data:`FIT`,
  :data:`STAGE_CODE`, :data:`FE_BENCH`). Editing a module outside them, or a
  comment, the formatting or a docstring, leaves it unchanged: those cannot
  change a result. What the computation imports (:func:`import_closure`) is
  checked against the declaration by a test, so a new dependency cannot escape
  its key.

Plus :func:`git_commit`, the commit recorded in every result. Nothing here
imports the packages it fingerprints (sources are read with :mod:`ast`), so
the pipeline can fingerprint the FE code without importing dolfinx.
"""
from __future__ import annotations

import ast
import dataclasses
import functools
import hashlib
import importlib.util
import json
import os
import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from forcecal import PROJECT_PACKAGES
from forcecal.errors import DataFileError
from forcecal.sections import REFERENCE_SECTIONS

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


def _roots(entries: tuple[str, ...]) -> dict[str, Path]:
    """``{top-level package: its folder}`` of the entries' packages and the project's."""
    roots = {p: package_root(p) for p in {e.split(".")[0] for e in entries}}
    roots.update({p: package_root(p) for p in PROJECT_PACKAGES
                  if p not in roots and importlib.util.find_spec(p) is not None})
    return roots


def _entry_modules(entry: str, roots: dict[str, Path], subpackages: bool) -> list[str]:
    """The module ``entry`` names, or a package's modules (its ``__init__`` first; those of
    its sub-packages too when ``subpackages``)."""
    path = module_file(entry, roots)
    if path is None:
        raise DataFileError(f"cannot fingerprint the code of {entry!r}: no source file")
    if path.name != "__init__.py":
        return [entry]
    return [entry] + [".".join((entry, *f.relative_to(path.parent).with_suffix("").parts[
                          :-1 if f.name == "__init__.py" else None]))
                      for f in sorted(path.parent.rglob("*.py"))
                      if "__pycache__" not in f.parts and f != path
                      and (subpackages or f.name != "__init__.py")]


def import_closure(entries: tuple[str, ...]) -> dict[str, Path]:
    """Every project module the ``entries`` import, transitively: ``{module name: file}``.

    An entry is a module, or a package standing for all of its modules.
    Imports are read from the source (:mod:`ast`), so nothing is imported and
    lazy imports inside functions count too. Only modules of the project's
    packages (and of the entries' own top-level packages) are followed; each
    module brings the ``__init__`` of its parent packages, which Python runs
    on import.
    """
    roots = _roots(entries)
    pending = [m for entry in entries for m in _entry_modules(entry, roots, subpackages=False)]
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


def declared_modules(entries: tuple[str, ...]) -> dict[str, Path]:
    """The modules ``entries`` name, ``{module name: file}``: each a module, or a package
    standing for every module in it (sub-packages included). Nothing else: not the parent
    packages' ``__init__``, not what they import."""
    roots = _roots(entries)
    return {m: module_file(m, roots) for entry in entries
            for m in _entry_modules(entry, roots, subpackages=True)}


def source_digest(path: Path, ignored: frozenset[str] = frozenset()) -> str:
    """SHA-256 of a module's syntax tree without docstrings.

    Comments, formatting and docstrings do not change what the code computes,
    so editing them must not discard a result; every other change (code,
    string constants such as messages) does. ``ignored``: names of top-level
    classes and functions left out as well (:meth:`CodeDependencies.ignored_definitions`).
    """
    return _tree_digest(path.read_text(), str(path), ignored)


def _without_docstrings(source: str, filename: str,
                        ignored: frozenset[str] = frozenset()) -> ast.Module:
    tree = ast.parse(source, filename)
    if ignored:
        tree.body = [node for node in tree.body
                     if not (isinstance(node, (ast.ClassDef, ast.FunctionDef))
                             and node.name in ignored)]
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if (isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef))
                and body and isinstance(body[0], ast.Expr)
                and isinstance(body[0].value, ast.Constant)
                and isinstance(body[0].value.value, str)):
            node.body = body[1:] or [ast.Pass()]
    return tree


@functools.lru_cache(maxsize=1024)  # keyed on the text: the stages share most of their modules
def _tree_digest(source: str, filename: str, ignored: frozenset[str] = frozenset()) -> str:
    tree = _without_docstrings(source, filename, ignored)
    return hashlib.sha256(ast.dump(tree).encode()).hexdigest()


def holds_no_code(path: Path) -> bool:
    """The module is its docstring (and comments) alone: running it computes nothing."""
    body = _without_docstrings(path.read_text(), str(path)).body
    return all(isinstance(node, ast.Pass) for node in body)


#: project modules a computation imports whose change cannot change its result, and why
#: (besides modules holding no code, :func:`holds_no_code`); every other module of a
#: computation's import closure must be one it declares (:meth:`CodeDependencies.undeclared`)
NOT_RESULT = {
    "forcecal": "the package's version string, its package list and the numba cache set-up",
    "forcecal.caches": "where numba keeps its compiled kernels (the same machine code)",
    "forcecal.logs": "which log records are shown, and how",
    "forcecal.failures": "how a failure is reported: its error line and exit status",
    "forcecal.provenance": "the keys themselves and the git commit recorded beside a result",
    "calibration.progress": "the progress bar and cost ticker on the terminal",
}


@dataclass(frozen=True)
class CodeDependencies:
    """The code one computation's result depends on: the code part of its cache key.

    Attributes:
        runs: the modules it executes (entry points, and those it starts as child
            processes); their import closure (:func:`import_closure`) must lie in ``reads``
            but for :data:`NOT_RESULT` and modules holding no code (a test checks it).
        reads: the packages and modules whose change can change its result
            (:func:`declared_modules`); their code alone is its key, so editing a module
            outside them (a helper of another stage, ``forcecal/__init__.py``) leaves it.
        sections: the scene sections it reads, or None for all: the classes of the others
            in ``forcecal.scene`` are left out of that module's digest (their keys cannot
            change its result, e.g. a new ``[calibration]`` key and the FE reference).

    The scene's refusals (:data:`forcecal.scene.REFUSALS`) are left out of every key: they
    only refuse a scene, so editing them cannot change a result computed for a scene they
    accept (one they now refuse is refused before any cached result is read).
    """
    runs: tuple[str, ...]
    reads: tuple[str, ...]
    sections: tuple[str, ...] | None = None

    def ignored_definitions(self) -> dict[str, frozenset[str]]:
        """``{module: names of top-level classes and functions}`` left out of its digest:
        the scene's refusals, and the classes of the sections it does not read."""
        from forcecal.scene import REFUSALS, SECTIONS
        unread = () if self.sections is None else (
            cls.__name__ for name, cls in SECTIONS.items() if name not in self.sections)
        return {"forcecal.scene": frozenset(REFUSALS).union(unread)}

    def digests(self) -> dict[str, str]:
        """``{file path relative to its package root: source_digest}`` of every module of
        ``reads`` (per file, so a cache can say which files changed)."""
        ignored = self.ignored_definitions()
        out = {}
        for name, path in declared_modules(self.reads).items():
            rel = path.relative_to(package_root(name.split(".")[0]))
            out[str(rel)] = source_digest(path, ignored.get(name, frozenset()))
        return dict(sorted(out.items()))

    def digest(self) -> str:
        """:meth:`digests` in one SHA-256."""
        return hashlib.sha256(json.dumps(self.digests(), sort_keys=True).encode()).hexdigest()

    def undeclared(self) -> list[str]:
        """Modules ``runs`` imports that are neither in ``reads`` nor known to leave its
        result alone: a dependency its key would miss (must be empty)."""
        declared = declared_modules(self.reads)
        return sorted(name for name, path in import_closure(self.runs).items()
                      if name not in declared and name not in NOT_RESULT
                      and not holds_no_code(path))

    def with_(self, runs: tuple[str, ...] = (), reads: tuple[str, ...] = ()
              ) -> CodeDependencies:
        """These dependencies and more: a computation that runs this one and more code."""
        return dataclasses.replace(self, runs=self.runs + runs, reads=self.reads + reads)


# The code each cached computation depends on, all in one place. A computation's key holds
# the code of what it declares, nothing else; tests/test_pipeline_units.py fails when one
# imports a module it does not declare.

#: the shared modules the FE reads: the scene and its sections, the mesh (and the generated
#: liver), the support and test-point rules, the schedules and indenter, the HDF5 files; the
#: preflight and failure records it writes into reference.h5 and the cost estimate they hold;
#: the errors that decide a failure; the free-free eigen-solve of the whole-body data
SHARED_FE = ("forcecal.scene", "forcecal.sections", "forcecal.mesh", "forcecal.liver_mesh",
             "forcecal.point_selection", "forcecal.problem",
             "forcecal.h5io", "forcecal.indenter", "forcecal.schedules", "forcecal.errors",
             "forcecal.preflight", "forcecal.fe_failures", "forcecal.cost", "forcecal.eigen")
#: and those the particle side reads besides: the BLAS thread count (the order of its sums)
SHARED_PARTICLE = SHARED_FE + ("forcecal.blas",)


def _runner(stage: str) -> tuple[str, ...]:
    """The pipeline modules that run ``stage`` and write its outputs."""
    return ("pipelines.runners.common", f"pipelines.runners.{stage}")


#: the FE experiments (per-experiment keys in reference.h5, :mod:`reference_fe.keys`)
FE = CodeDependencies(runs=("reference_fe.run", "reference_fe.__main__"),
                      reads=("reference_fe",) + SHARED_FE, sections=REFERENCE_SECTIONS)
#: a calibration's fit (its checkpoint key, :mod:`calibration.provenance`)
FIT = CodeDependencies(runs=("calibration.core", "calibration.worker"),
                       reads=("calibration", "particle") + SHARED_PARTICLE)
#: the pipeline's stages (:mod:`pipelines.stages`), each with its runner
STAGE_CODE = {
    "reference": FE.with_(runs=("pipelines.runners.reference",), reads=_runner("reference")),
    "calibrate": FIT.with_(runs=("pipelines.runners.calibrate",), reads=_runner("calibrate")),
    "gravity": FIT.with_(runs=("pipelines.runners.gravity",),
                         reads=("pipelines.gravity",) + _runner("gravity")),
    "report": FIT.with_(runs=("pipelines.runners.report",),
                        reads=("pipelines.report", "pipelines.gravity", "pipelines.dynamics",
                               "pipelines.fields", "pipelines.figures", "pipelines.realtime",
                               "pipelines.verdict", "pipelines.bench.particle_engine")
                        + _runner("report")),
}
#: the benchmark's FE computations: the reference and the discretisation study
FE_BENCH = FE.with_(runs=("reference_fe.sensitivity",))


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
