"""HDF5 files exchanged between the stages, written atomically and read with checks.

``reference.h5`` (written by ``reference_fe``, read by ``particle`` and
``calibration``) is described here once; ``docs/data-files.md``
is the prose version of :func:`write_reference`. Every dataset carries a
``unit`` attribute. Files are written to ``<name>.tmp-<pid>`` and renamed into
place, so a reader never sees a half-written file; a truncated, corrupt, wrong
kind or mismatched file, or one missing a dataset or attribute, raises
:class:`~forcecal.errors.DataFileError` naming the path inside the file.

A reference stores the scene settings it was computed with (``[material]``,
``[fe]``, ``[gravity]``, the indenter) as attributes; readers check them
against their scene with :func:`check_reference_settings`.

A reference holds the experiments its scene asked for (``experiments``): the
``/indentation`` group always, ``/relaxation``, the datasets of ``/gravity`` and the
``/body`` and the ``/second_support`` groups only when computed; the root attribute
``experiments`` (JSON list) names those present, ``experiment_keys`` (JSON) their keys
(:mod:`reference_fe.keys`). A file without the attribute (written before experiments were
optional) holds the four of :data:`~forcecal.scene.DEFAULT_EXPERIMENTS`.
``/second_support`` (:class:`SecondSupportResult`) holds the gravity test with the
``[second_support]`` vertices clamped: its keys as attributes, the subgroup ``gravity`` (the
``[gravity]`` keys, ``tracked_node`` resolved for this support), the datasets ``fixed``
(F2,), ``static_displacement`` (N, 3) m, ``time`` (S,) s and ``displacement`` (S, N, 3) m.
``/floor`` (:class:`FloorResult`, experiment ``floor``) holds the discretisation floor: the
gravity test computed by vertex-dof FE elements on the particle mesh
(:mod:`reference_fe.floor`); attributes ``elements`` (JSON list) and ``quadrature_degree``,
the subgroup ``gravity`` (the ``[gravity]`` keys it ran with) and one subgroup per element
with the attributes ``seconds`` and ``part_seconds`` (JSON) and either the datasets
``static_displacement`` (N, 3) m, ``time`` (S,) s and ``displacement`` (S, N, 3) m or the
attribute ``failed`` (why its run failed). With the second support, the attribute
``second_support_tracked_node`` and per element the subgroup ``second_support`` (the same three
datasets, or ``failed``); with the held-out curves, the dataset ``held_out_vertices`` (H,) and
per element the subgroup ``held_out`` (``indentation_force`` (H, D, 3) N,
``relaxation_force`` (H, T, 3) N, NaN rows at the points whose attribute ``failed``, JSON
{vertex: reason}, names).

What failed in the FE stage is recorded too: ``fe_failures`` (JSON,
:class:`forcecal.fe_failures.FEFailures`: test points replaced or dropped, the gravity
test that failed, which leaves both gravity experiments out, the second support's test that
failed, which leaves ``second_support`` out) with ``failed_experiment_keys`` (JSON, the keys
the failed experiments were computed with), and ``mesh_preflight`` (JSON,
:func:`forcecal.preflight.mesh_preflight`). The test points stored are the ones the curves
belong to (replacements in place of the failed points, dropped points left out).
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime
import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import h5py
import numpy as np

import forcecal
from forcecal.errors import DataFileError, MeshError, SceneError
from forcecal.mesh import TetMesh, check_mesh
from forcecal.problem import Problem, tracked_node_by_rule
from forcecal.fe_failures import FEFailures
from forcecal.scene import (DEFAULT_EXPERIMENTS, EXPERIMENTS, GRAVITY_EXPERIMENTS, SECTIONS,
                            FESection, GravitySection, MaterialSection, Scene,
                            SecondSupportSection, section_from_values)
from forcecal.schedules import record_times

REFERENCE_KIND = "forcecal.reference"
# 2: the [fe] and [gravity] settings and the indenter are stored (and checked on read)
REFERENCE_SCHEMA = 2


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it onto ``path`` if the block succeeds."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DataFileError(f"cannot create output folder {path.parent}: {exc}") from exc
    if not os.access(path.parent, os.W_OK):
        raise DataFileError(f"output folder {path.parent} is not writable")
    tmp = path.with_name(f"{path.name}{TMP_MARK}{os.getpid()}")
    try:
        yield tmp
        os.replace(tmp, path)
    except OSError as exc:  # disk full, quota, I/O error: nothing is left half-written
        raise DataFileError(f"cannot write {path}: {exc.strerror or exc} (nothing was written; "
                            "free space or fix the folder, then rerun)") from exc
    finally:
        if tmp.exists():
            tmp.unlink()


def check_output_file(path: str | Path, option: str = "--out") -> Path:
    """Refuse, before any work, an output file path that cannot be written: a directory, a
    parent that is a file or cannot be created, or a folder that is not writable (the
    command-line ``option`` names it). Creates the parent folder; returns the path.

    Raises:
        DataFileError: naming the path, the problem and what is expected.
    """
    path = Path(path)
    if path.is_dir():
        raise DataFileError(f"{option} {path} is a directory; give the path of the file to "
                            f"write (e.g. {path / 'reference.h5'} or {path / 'params.h5'})")
    parent = path.parent
    if parent.exists() and not parent.is_dir():
        raise DataFileError(f"{option} {path}: its folder {parent} is a file, not a directory")
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DataFileError(f"{option} {path}: cannot create its folder {parent}: "
                            f"{exc.strerror or exc}") from None
    if not os.access(parent, os.W_OK | os.X_OK):
        raise DataFileError(f"{option} {path}: its folder {parent} is not writable")
    return path


#: what :func:`atomic_path` puts between a file's name and the writing process's id
TMP_MARK = ".tmp-"


def remove_stale_temporaries(folder: str | Path) -> list[Path]:
    """Delete the temporary files of :func:`atomic_path` under ``folder`` whose writer is gone
    (a killed run, a machine switched off); returns them. A live writer's file is kept."""
    removed = []
    for tmp in Path(folder).rglob(f"*{TMP_MARK}*"):
        pid = tmp.name.rpartition(TMP_MARK)[2]
        if not pid.isdigit() or _process_alive(int(pid)) or not tmp.is_file():
            continue
        try:
            tmp.unlink()
            removed.append(tmp)
        except OSError:
            pass
    return removed


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


@contextlib.contextmanager
def atomic_h5(path: str | Path, kind: str, schema: int) -> Iterator[h5py.File]:
    """Open a new HDF5 file for writing; it appears at ``path`` only once complete."""
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as fh:
            fh.attrs["kind"] = kind
            fh.attrs["schema_version"] = schema
            fh.attrs["forcecal_version"] = forcecal.__version__
            fh.attrs["created"] = datetime.datetime.now(datetime.timezone.utc).isoformat()
            yield fh


@contextlib.contextmanager
def open_h5(path: str | Path, kind: str, schema: int) -> Iterator[h5py.File]:
    """Open an HDF5 file written by :func:`atomic_h5`, checking its kind and schema version."""
    path = Path(path)
    if not path.is_file():
        raise DataFileError(f"{path} does not exist")
    try:
        fh = h5py.File(path, "r")
    except OSError as exc:
        raise DataFileError(f"{path} is not a readable HDF5 file (corrupt or truncated?): "
                            f"{exc}") from exc
    with fh:
        got = fh.attrs.get("kind")
        if got != kind:
            raise DataFileError(f"{path} is not a {kind} file (kind = {got!r})")
        version = fh.attrs.get("schema_version")
        if version != schema:
            raise DataFileError(f"{path} has schema version {version}, this code reads {schema}; "
                                "recompute it")
        try:
            yield fh
        except KeyError as exc:  # h5py's answer to a group or attribute the file lacks
            raise DataFileError(f"{path}: {exc} (a group or attribute of the {kind} schema is "
                                "missing: corrupt file, or not written by forcecal?)") from exc


def put(group: h5py.Group, name: str, data: Any, unit: str, doc: str = "") -> h5py.Dataset:
    """Write a dataset with its unit (and an optional one-line description)."""
    ds = group.create_dataset(name, data=np.asarray(data))
    ds.attrs["unit"] = unit
    if doc:
        ds.attrs["doc"] = doc
    return ds


def get(fh: h5py.File, name: str, shape: tuple | None = None, *, finite: bool = True,
        dtype: str | None = None) -> np.ndarray:
    """Read dataset ``name`` checking presence, shape (None entries are free) and finiteness."""
    where = f"{fh.filename}:/{name}"
    if name not in fh:
        raise DataFileError(f"{where} is missing")
    try:
        arr = fh[name][()]
    except Exception as exc:  # h5py raises OSError/KeyError/RuntimeError on damaged data
        raise DataFileError(f"{where} cannot be read (corrupt file?): {exc}") from exc
    arr = np.asarray(arr)
    if shape is not None:
        if arr.ndim != len(shape) or any(s is not None and s != a for s, a in zip(shape, arr.shape)):
            raise DataFileError(f"{where} has shape {arr.shape}, expected {shape}")
    if dtype == "int":
        if not np.issubdtype(arr.dtype, np.integer):
            raise DataFileError(f"{where} must hold integers, has {arr.dtype}")
        arr = arr.astype(np.int64)
    elif dtype == "float":
        arr = arr.astype(np.float64)
    if finite and np.issubdtype(arr.dtype, np.floating) and not np.all(np.isfinite(arr)):
        bad = int(np.count_nonzero(~np.isfinite(arr)))
        raise DataFileError(f"{where} contains {bad} NaN/inf values")
    return arr


def group(fh: h5py.File, name: str) -> h5py.Group:
    """Group ``name`` of ``fh``; DataFileError naming it if it is missing or not a group."""
    try:
        g = fh[name] if name in fh else None
    except Exception as exc:  # h5py raises several types on damaged metadata
        raise DataFileError(f"{fh.filename}:/{name} cannot be read (corrupt file?): "
                            f"{exc}") from exc
    if not isinstance(g, h5py.Group):
        raise DataFileError(f"{fh.filename}:/{name} is missing")
    return g


def attr(obj: h5py.Group | h5py.File, name: str) -> Any:
    """Attribute ``name`` of a group or file as a plain value (numpy scalars unwrapped);
    DataFileError naming the file, group and attribute if it is missing or unreadable."""
    where = f"{obj.file.filename}:{obj.name} attribute {name!r}"
    try:
        present = name in obj.attrs
        value = obj.attrs[name] if present else None
    except Exception as exc:  # h5py raises several types on damaged metadata
        raise DataFileError(f"{where} cannot be read (corrupt file?): {exc}") from exc
    if not present:
        raise DataFileError(f"{where} is missing")
    return value.item() if isinstance(value, np.generic) else value


_REQUIRED = object()


def json_attr(obj: h5py.Group | h5py.File, name: str, default: Any = _REQUIRED) -> Any:
    """Attribute ``name`` holding JSON text (:func:`attr`), decoded; ``default`` if it is
    absent and a default is given. DataFileError naming the file, group and attribute if it
    is missing (without a default), unreadable or not JSON."""
    if default is not _REQUIRED and name not in obj.attrs:
        return default
    raw = attr(obj, name)
    try:
        return json.loads(raw)
    except (TypeError, ValueError) as exc:
        raise DataFileError(f"{obj.file.filename}:{obj.name} attribute {name!r} = {raw!r:.80} "
                            f"is not JSON text (corrupt file?)") from exc


def write_section(g: h5py.Group, section: Any) -> None:
    """Every key of a scene section as an attribute of ``g`` (lists as float arrays), and
    their units (from the key declarations) as the JSON attribute ``units``."""
    units = {}
    for f in dataclasses.fields(section):
        value = getattr(section, f.name)
        g.attrs[f.name] = np.asarray(value, dtype=float) if isinstance(value, tuple) else value
        if f.metadata["unit"]:
            units[f.name] = f.metadata["unit"]
    if units:
        g.attrs["units"] = json.dumps(units)


def read_section(g: h5py.Group, name: str) -> Any:
    """Scene section ``name`` from the attributes of ``g`` (:func:`write_section`), with the
    type and range checks of a scene file; DataFileError naming what is missing or wrong."""
    values = {}
    for f in dataclasses.fields(SECTIONS[name]):
        value = attr(g, f.name)
        values[f.name] = value.tolist() if isinstance(value, np.ndarray) else value
    try:
        return section_from_values(name, values, f"{g.file.filename}:{g.name}")
    except SceneError as exc:
        raise DataFileError(f"{exc} (corrupt file?)") from None


@dataclass(frozen=True, eq=False)
class IndentationCurves:
    """Quasi-static indentation of every test point (no gravity, long-term material).

    Attributes:
        displacement: (S,) float64, indentation depth of the test vertex along its
            inward normal at each sample [m] (increasing, first sample > 0).
        force: (P, S, 3) float64, force the indenter applies to the test vertex
            (= reaction of the tissue, reversed) [N].
        force_normal: (P, S) float64, ``force . inward_normal`` [N]; positive when pushing in.
    """
    displacement: np.ndarray
    force: np.ndarray
    force_normal: np.ndarray
    indenter: str = "vertex"  # ``indentation.indenter`` (relaxation uses the same one)
    radius: float = 0.0  # ``indentation.radius`` [m] (punch; 0 for the vertex)


@dataclass(frozen=True, eq=False)
class RelaxationCurves:
    """Ramp-and-hold indentation (quasi-static, viscoelastic material).

    Attributes:
        time: (S,) float64, sample times [s], increasing, first > 0.
        displacement: (S,) float64, prescribed depth at those times [m].
        force: (P, S, 3) float64, indenter force on the test vertex [N].
        force_normal: (P, S) float64, its inward-normal component [N].
    """
    time: np.ndarray
    displacement: np.ndarray
    force: np.ndarray
    force_normal: np.ndarray


@dataclass(frozen=True, eq=False)
class GravityResult:
    """Sag of the organ under gravity, base fixed.

    Attributes:
        static_displacement: (N, 3) float64, static equilibrium displacement of every vertex [m]
            (long-term material); None when ``gravity_static`` was not computed.
        time: (S,) float64, sample times of the dynamic run [s], starting at 0 (rest); None
            when ``gravity_dynamic`` was not computed (and so is ``displacement``).
        displacement: (S, N, 3) float64, vertex displacements of the dynamic run [m].
        settings: the scene's ``[gravity]`` keys the runs were computed with (acceleration,
            load steps, duration, FE step, record interval), ``tracked_node`` resolved to the
            vertex whose history the reports compare.
    """
    static_displacement: np.ndarray | None
    time: np.ndarray | None
    displacement: np.ndarray | None
    settings: GravitySection

    @property
    def tracked_node(self) -> int:
        """Vertex whose displacement history the reports compare."""
        return int(self.settings.tracked_node)


#: the moduli of the body modes, in the order of :attr:`BodyResult.frequencies`' rows
BODY_MODULI = ("instantaneous", "long_term")


@dataclass(frozen=True, eq=False)
class BodyResult:
    """Whole-body data (experiment ``body``, computed by :mod:`reference_fe.body`): natural
    modes about the rest state and static body loads, both with the scene's support.

    Attributes:
        frequencies: (2, M) float64, the M lowest natural frequencies [Hz], ascending, at the
            instantaneous (row 0) and the long-term (row 1) moduli (:data:`BODY_MODULI`).
        shapes: (2, M, N, 3) float64, their mode shapes at the particle vertices,
            mass-normalised with the FE's consistent mass [1/sqrt(kg)].
        load_directions: (L, 3) float64, unit directions of the static body loads (the two
            perpendicular to the scene's gravity).
        load_acceleration: magnitude of the loads' acceleration [m/s^2] (the scene's |g|).
        load_displacement: (L, N, 3) float64, static displacement of every vertex under each
            load [m] (long-term material, nonlinear).
        loaded_frequencies: (L, M) float64, the M lowest frequencies [Hz] of small motions
            about each load's equilibrium (instantaneous incremental moduli), ascending.
        loaded_shapes: (L, M, N, 3) float64, their shapes, normalised as ``shapes``.
        free_frequencies: (2, M) float64, the M lowest natural frequencies [Hz] of the
            unsupported body (free-free: its six rigid modes left out), ascending, at the two
            moduli as ``frequencies``; None in a reference computed without them.
        free_shapes: (2, M, N, 3) float64, their shapes, normalised as ``shapes``; None with
            ``free_frequencies``.
        load_failure: why the static body loads are absent (L = 0: the FE could not hold the
            body under one of them, e.g. a seat that lets it swing over sideways; the modes
            are kept), None when they were computed.
    """
    frequencies: np.ndarray
    shapes: np.ndarray
    load_directions: np.ndarray
    load_acceleration: float
    load_displacement: np.ndarray
    loaded_frequencies: np.ndarray
    loaded_shapes: np.ndarray
    free_frequencies: np.ndarray | None = None
    free_shapes: np.ndarray | None = None
    load_failure: str | None = None

    @property
    def load_accelerations(self) -> np.ndarray:
        """(L, 3) the loads' accelerations [m/s^2]."""
        return self.load_acceleration * self.load_directions


@dataclass(frozen=True, eq=False)
class SecondSupportResult:
    """The gravity test with the second support (experiment ``second_support``): the organ
    under the same weight, the ``[second_support]`` vertices clamped instead of ``[fixed]``'s.

    Attributes:
        section: the scene's ``[second_support]`` keys it was computed with.
        fixed: (F2,) int64, its clamped vertices (:func:`forcecal.problem.second_support`).
        runs: its static sag and release, as the gravity test's (both present); their
            ``settings`` are the scene's ``[gravity]`` with ``tracked_node`` resolved for this
            support.
    """
    section: SecondSupportSection
    fixed: np.ndarray
    runs: GravityResult


#: the discretisation floor's elements (:mod:`reference_fe.floor`): the locking-free vertex-dof
#: element, the floor itself, first; plain P1 next to it, so its locking is visible
FLOOR_ELEMENTS = ("ANP", "P1")


#: the parts of a floor element's compute time (:attr:`FloorResult.part_seconds`)
FLOOR_PARTS = ("build", "gravity", "second_support", "held_out")


@dataclass(frozen=True, eq=False)
class HeldOutCurves:
    """Force curves of the held-out test points (the discretisation floor's, or the reference's
    to measure them against).

    Attributes:
        vertices: (H,) int64, the test vertices.
        indentation: (H, D, 3) float64, indenter force at the indentation depths [N].
        relaxation: (H, T, 3) float64, indenter force at the relaxation times [N]; None
            without the relaxation experiment.
        failed: vertex -> why its curves failed (their rows are NaN).
    """
    vertices: np.ndarray
    indentation: np.ndarray
    relaxation: np.ndarray | None
    failed: dict[int, str] = field(default_factory=dict)


@dataclass(frozen=True, eq=False)
class FloorResult:
    """The discretisation floor (experiment ``floor``, :mod:`reference_fe.floor`): the
    gravity test, with the second support the second-support test and the held-out test
    points' force curves, computed on the particle mesh by FE elements whose only
    displacement dofs are the vertices'.

    Attributes:
        runs: element -> its static sag and release (both present; ``settings`` the scene's
            ``[gravity]`` with the reference's tracked node), for the elements that ran.
        failed: element -> why its gravity test failed (Newton, an unstable support).
        seconds: element -> compute time of all its runs [s] (model build included).
        quadrature_degree: of the elements' residual.
        second_support: element -> its second-support sag and release (``settings`` with the
            second support's tracked node); empty when the scene does not run that test.
        second_support_failed: element -> why its second-support test failed.
        held_out: element -> its held-out curves; empty when not computed.
        part_seconds: element -> {part of :data:`FLOOR_PARTS`: compute time [s]}.
    """
    runs: dict[str, GravityResult]
    failed: dict[str, str]
    seconds: dict[str, float]
    quadrature_degree: int
    second_support: dict[str, GravityResult] = field(default_factory=dict)
    second_support_failed: dict[str, str] = field(default_factory=dict)
    held_out: dict[str, HeldOutCurves] = field(default_factory=dict)
    part_seconds: dict[str, dict[str, float]] = field(default_factory=dict)

    @property
    def elements(self) -> tuple[str, ...]:
        """Every element of the floor, those that ran first."""
        return tuple(self.runs) + tuple(e for e in self.failed if e not in self.runs)

    @property
    def has_second_support(self) -> bool:
        """Whether the floor ran the second-support test."""
        return bool(self.second_support or self.second_support_failed)


@dataclass(frozen=True, eq=False)
class Reference:
    """Everything in ``reference.h5``.

    ``fe`` is the ``[fe]`` section the curves were computed with (None for a reference not
    computed by the FE, e.g. :func:`calibration.synthetic.synthetic_reference`).
    ``relaxation`` is None, and ``gravity`` None or partly None, for experiments not
    computed (:attr:`experiments` lists those present).
    """
    problem: Problem
    material: MaterialSection
    indentation: IndentationCurves
    relaxation: RelaxationCurves | None
    gravity: GravityResult | None
    meta: dict[str, Any] = field(default_factory=dict)
    fe: FESection | None = None
    body: BodyResult | None = None
    second_support: SecondSupportResult | None = None
    floor: FloorResult | None = None

    @property
    def experiments(self) -> tuple[str, ...]:
        """The experiments this reference holds, in :data:`~forcecal.scene.EXPERIMENTS` order."""
        g = self.gravity
        present = {"indentation": True, "relaxation": self.relaxation is not None,
                   "gravity_static": g is not None and g.static_displacement is not None,
                   "gravity_dynamic": g is not None and g.time is not None,
                   "body": self.body is not None,
                   "second_support": self.second_support is not None,
                   "floor": self.floor is not None}
        return tuple(e for e in EXPERIMENTS if present[e])

    @property
    def fe_failures(self) -> FEFailures:
        """The FE test points replaced or dropped and the gravity failure (root attribute
        ``fe_failures``, :mod:`forcecal.fe_failures`; none recorded: nothing failed)."""
        return FEFailures.from_json(self.meta.get("fe_failures"), "reference.h5")

    @property
    def mesh_preflight(self) -> dict | None:
        """The mesh preflight the FE stage logged (root attribute ``mesh_preflight``,
        :func:`forcecal.preflight.mesh_preflight`), or None in a file without it."""
        text = self.meta.get("mesh_preflight")
        return None if text is None else json.loads(text)

    def require(self, experiment: str, path: str | Path = "reference.h5") -> None:
        """Raise :class:`DataFileError` if ``experiment`` is not in this reference (naming the
        FE failure that left it out, if one did)."""
        if experiment not in self.experiments:
            failures = self.fe_failures
            failed = (failures.gravity if experiment in GRAVITY_EXPERIMENTS else
                      failures.second_support if experiment == "second_support" else None)
            if failed is not None:
                test = "gravity" if experiment in GRAVITY_EXPERIMENTS else "second-support"
                raise DataFileError(f"{path} has no {experiment} results: the FE {test} test "
                                    f"failed ({failed['experiment']}: {failed['reason']})")
            raise DataFileError(f"{path} has no {experiment} results (it holds "
                                f"{list(self.experiments)}); add {experiment!r} to the scene's "
                                "experiments and rerun the reference")


def section_differences(section: str, stored: Any, wanted: Any,
                        ignore: tuple[str, ...] = ()) -> list[str]:
    """``"<section>.<key> = <stored> (scene: <wanted>)"`` for every key of two instances of a
    scene section class that differs (``ignore``: keys not compared)."""
    return [f"{section}.{f.name} = {getattr(stored, f.name)!r} (scene: "
            f"{getattr(wanted, f.name)!r})" for f in dataclasses.fields(stored)
            if f.name not in ignore and getattr(stored, f.name) != getattr(wanted, f.name)]


def check_reference_settings(ref: Reference, scene: Scene, path: str | Path) -> None:
    """Refuse a reference computed with other FE, gravity or indenter settings than ``scene``'s.

    Compares ``[fe]`` (element, quadrature degree, Newton settings), ``[gravity]``
    (acceleration, load steps, duration, FE step, record interval, tracked node) and
    ``indentation.indenter``; the material, schedules and test points are the caller's
    (:func:`calibration.core.load_checked_reference`).

    Raises:
        DataFileError: naming every key that differs, with both values.
    """
    differ = []

    def compare(section: str, stored: Any, wanted: Any, keys: tuple[str, ...]) -> None:
        for k in keys:
            got, want = getattr(stored, k), getattr(wanted, k)
            if got != want:
                differ.append(f"{section}.{k} = {got!r} (scene: {want!r})")

    if ref.indentation.indenter != scene.indentation.indenter:
        differ.append(f"indentation.indenter = {ref.indentation.indenter!r} "
                      f"(scene: {scene.indentation.indenter!r})")
    if ref.indentation.radius != scene.indentation.radius:
        differ.append(f"indentation.radius = {ref.indentation.radius!r} "
                      f"(scene: {scene.indentation.radius!r})")
    if ref.fe is not None:
        compare("fe", ref.fe, scene.fe, tuple(f.name for f in dataclasses.fields(FESection)))
    # a reference may hold gravity runs the scene does not ask for (a superset): not compared
    if ref.gravity is not None and (scene.runs("gravity_static") or scene.runs("gravity_dynamic")):
        wanted = scene.gravity
        if isinstance(wanted.tracked_node, str):
            wanted = dataclasses.replace(wanted, tracked_node=tracked_node_by_rule(
                ref.problem.mesh, ref.problem.fixed, wanted.tracked_node))
        compare("gravity", ref.gravity.settings, wanted,
                tuple(f.name for f in dataclasses.fields(GravitySection)))
    second = ref.second_support
    if second is not None and scene.runs("second_support"):
        compare("second_support", second.section, scene.second_support,
                tuple(f.name for f in dataclasses.fields(SecondSupportSection)))
        compare("gravity", second.runs.settings, scene.gravity,  # tracked node: its own rule
                tuple(f.name for f in dataclasses.fields(GravitySection)
                      if f.name != "tracked_node"))
    if differ:
        raise DataFileError(f"{path} was computed with other settings than the scene's: "
                            + "; ".join(differ) + "; recompute the reference")


def write_problem(fh: h5py.File, problem: Problem) -> None:
    """Write the /mesh and /test_points groups (shared by every forcecal HDF5 file)."""
    m = problem.mesh
    g = fh.create_group("mesh")
    put(g, "vertices", m.vertices, "m", "vertex coordinates (N, 3)")
    put(g, "tets", m.tets, "1", "vertex ids of each positively oriented tet (T, 4)")
    put(g, "edges", m.edges, "1", "unique edges i < j, sorted; one connector each (E, 2)")
    put(g, "fixed", problem.fixed, "1", "ids of the fixed vertices (F,)")
    g.attrs["fingerprint"] = m.fingerprint()
    t = fh.create_group("test_points")
    put(t, "nodes", problem.test_points, "1", "calibration points, then held-out points (P,)")
    put(t, "is_calibration", np.r_[np.ones(len(problem.calibration), bool),
                                   np.zeros(len(problem.held_out), bool)], "1",
        "True for calibration points, False for held-out points (P,)")
    put(t, "normals", problem.normals, "1", "inward unit normals = indentation directions (P, 3)")
    t.attrs["tracked_node"] = problem.tracked_node
    for which, fraction in problem.coverage.items():  # derived, for readers (not read back)
        t.attrs[f"{which}_coverage"] = fraction


def read_problem(fh: h5py.File) -> Problem:
    """Read /mesh and /test_points back, re-checking the mesh."""
    vertices = get(fh, "mesh/vertices", (None, 3), dtype="float")
    tets = get(fh, "mesh/tets", (None, 4), dtype="int")
    try:
        mesh = check_mesh(TetMesh(vertices, tets))
    except MeshError as exc:
        raise DataFileError(f"{fh.filename}: stored mesh is invalid: {exc}") from None
    stored_fp = attr(group(fh, "mesh"), "fingerprint")
    if stored_fp != mesh.fingerprint():
        raise DataFileError(f"{fh.filename}: mesh fingerprint mismatch (file damaged or edited)")
    edges = get(fh, "mesh/edges", (None, 2), dtype="int")
    if not np.array_equal(edges, mesh.edges):
        raise DataFileError(f"{fh.filename}: /mesh/edges do not match the tets")
    fixed = get(fh, "mesh/fixed", (None,), dtype="int")
    nodes = get(fh, "test_points/nodes", (None,), dtype="int")
    is_cal = get(fh, "test_points/is_calibration", (len(nodes),)).astype(bool)
    tracked = attr(group(fh, "test_points"), "tracked_node")
    if not isinstance(tracked, int) or not 0 <= tracked < mesh.n_vertices:
        raise DataFileError(f"{fh.filename}: tracked node {tracked} is not a vertex")
    problem = Problem(mesh=mesh, fixed=fixed, calibration=nodes[is_cal], held_out=nodes[~is_cal],
                      tracked_node=tracked)
    normals = get(fh, "test_points/normals", (len(nodes), 3), dtype="float")
    if not np.allclose(normals, problem.normals, atol=1e-12):
        raise DataFileError(f"{fh.filename}: stored normals do not match the mesh")
    return problem


def write_reference(path: str | Path, ref: Reference) -> None:
    """Write ``reference.h5`` atomically (schema: see module docstring and docs/data-files.md)."""
    p = ref.problem
    n_pts, n_v = len(p.test_points), p.mesh.n_vertices
    ind, rel = ref.indentation, ref.relaxation
    _check_shape("indentation.force", ind.force, (n_pts, len(ind.displacement), 3))
    _check_shape("indentation.force_normal", ind.force_normal, (n_pts, len(ind.displacement)))
    if rel is not None:
        _check_shape("relaxation.force", rel.force, (n_pts, len(rel.time), 3))
        _check_shape("relaxation.force_normal", rel.force_normal, (n_pts, len(rel.time)))
        _check_shape("relaxation.displacement", rel.displacement, (len(rel.time),))
    for name, arr in (("indentation", ind.force), ("relaxation", None if rel is None
                                                   else rel.force)):
        if arr is not None and not np.all(np.isfinite(arr)):
            raise DataFileError(f"refusing to write {path}: {name} forces contain NaN/inf")
    if ref.gravity is not None and ref.gravity.settings.tracked_node != p.tracked_node:
        raise DataFileError(f"refusing to write {path}: gravity tracked node "
                            f"{ref.gravity.settings.tracked_node!r} is not the problem's "
                            f"{p.tracked_node}")
    with atomic_h5(path, REFERENCE_KIND, REFERENCE_SCHEMA) as fh:
        for k, v in ref.meta.items():
            fh.attrs[k] = v
        fh.attrs["experiments"] = json.dumps(list(ref.experiments))
        write_problem(fh, p)
        write_section(fh.create_group("material"), ref.material)
        if ref.fe is not None:
            write_section(fh.create_group("fe"), ref.fe)
        g = fh.create_group("indentation")
        g.attrs["indenter"] = ind.indenter
        g.attrs["radius"] = float(ind.radius)
        put(g, "displacement", ind.displacement, "m", "depth along the inward normal (S,)")
        put(g, "force", ind.force, "N", "indenter force on the test vertex (P, S, 3)")
        put(g, "force_normal", ind.force_normal, "N", "force . inward normal (P, S)")
        if rel is not None:
            g = fh.create_group("relaxation")
            put(g, "time", rel.time, "s", "sample times (S,)")
            put(g, "displacement", rel.displacement, "m", "prescribed depth (S,)")
            put(g, "force", rel.force, "N", "indenter force on the test vertex (P, S, 3)")
            put(g, "force_normal", rel.force_normal, "N", "force . inward normal (P, S)")
        if ref.gravity is not None:
            gr = ref.gravity
            g = fh.create_group("gravity")
            write_section(g, gr.settings)
            if gr.static_displacement is not None:
                _check_shape("gravity.static_displacement", gr.static_displacement, (n_v, 3))
                put(g, "static_displacement", gr.static_displacement, "m",
                    "static sag of every vertex (N, 3)")
            if gr.time is not None:
                _check_shape("gravity.displacement", gr.displacement, (len(gr.time), n_v, 3))
                put(g, "time", gr.time, "s", "dynamic run sample times, from rest at 0 (S,)")
                put(g, "displacement", gr.displacement, "m",
                    "dynamic vertex displacements (S, N, 3)")
        if ref.body is not None:
            write_body(fh.create_group("body"), ref.body, n_v)
        if ref.second_support is not None:
            _write_second_support(fh, ref.second_support, n_v)
        if ref.floor is not None:
            _write_floor(fh, ref.floor, n_v, ref.problem.tracked_node)


def _write_floor(fh: h5py.File, floor: FloorResult, n_v: int, tracked_node: int) -> None:
    """The ``/floor`` group (:class:`FloorResult`; module docstring); ``tracked_node`` the
    reference's (the scene's support's), for the ``gravity`` settings when only the second
    support's runs carry them (every element's own gravity test failed)."""
    g = fh.create_group("floor")
    g.attrs["elements"] = json.dumps(list(floor.elements))
    g.attrs["quadrature_degree"] = int(floor.quadrature_degree)
    settings = next(iter(floor.runs.values())).settings if floor.runs else None
    if settings is None and floor.second_support:
        settings = dataclasses.replace(next(iter(floor.second_support.values())).settings,
                                       tracked_node=int(tracked_node))
    if settings is not None:
        write_section(g.create_group("gravity"), settings)
    if floor.has_second_support:
        g.attrs["second_support_tracked_node"] = int(next(iter(
            floor.second_support.values())).tracked_node) if floor.second_support else -1
    vertices = next((c.vertices for c in floor.held_out.values()), None)
    if vertices is not None:
        put(g, "held_out_vertices", vertices, "1", "the held-out test vertices (H,)")
    for element in floor.elements:
        e = g.create_group(element)
        e.attrs["seconds"] = float(floor.seconds.get(element, 0.0))
        e.attrs["part_seconds"] = json.dumps(floor.part_seconds.get(element, {}))
        if element in floor.failed:
            e.attrs["failed"] = floor.failed[element]
        else:
            _write_floor_runs(e, floor.runs[element], n_v, element)
        if element in floor.second_support_failed:
            e.create_group("second_support").attrs["failed"] = \
                floor.second_support_failed[element]
        elif element in floor.second_support:
            _write_floor_runs(e.create_group("second_support"), floor.second_support[element],
                              n_v, f"{element}, second support")
        if element in floor.held_out:
            curves = floor.held_out[element]
            if not np.array_equal(curves.vertices, vertices):
                raise DataFileError(f"floor.{element}.held_out is on vertices "
                                    f"{curves.vertices.tolist()}, the others' on "
                                    f"{vertices.tolist()}")
            h = e.create_group("held_out")
            h.attrs["failed"] = json.dumps({str(v): r for v, r in curves.failed.items()})
            put(h, "indentation_force", curves.indentation, "N",
                f"indenter force at the indentation depths, {element} (H, D, 3); NaN: failed")
            if curves.relaxation is not None:
                put(h, "relaxation_force", curves.relaxation, "N",
                    f"indenter force at the relaxation times, {element} (H, T, 3); NaN: failed")


def _write_floor_runs(g: h5py.Group, runs: GravityResult, n_v: int, what: str) -> None:
    """A floor element's static sag and release (``/floor/<element>`` or its
    ``second_support``)."""
    _check_shape(f"floor {what} static_displacement", runs.static_displacement, (n_v, 3))
    _check_shape(f"floor {what} displacement", runs.displacement, (len(runs.time), n_v, 3))
    put(g, "static_displacement", runs.static_displacement, "m",
        f"static sag of every vertex, {what} on the particle mesh (N, 3)")
    put(g, "time", runs.time, "s", "release sample times, from rest at 0 (S,)")
    put(g, "displacement", runs.displacement, "m",
        f"release vertex displacements, {what} on the particle mesh (S, N, 3)")


def _read_floor(fh: h5py.File, path: str | Path, n_v: int) -> FloorResult:
    """The ``/floor`` group back, checked (:func:`_write_floor`)."""
    g = group(fh, "floor")
    elements = json_attr(g, "elements")
    if not isinstance(elements, list) or not elements:
        raise DataFileError(f"{path}:/floor attribute elements = {elements!r} is not a "
                            "non-empty JSON list")
    runs, failed, seconds, parts = {}, {}, {}, {}
    support, support_failed, held_out = {}, {}, {}
    settings = read_section(group(fh, "floor/gravity"), "gravity") if "gravity" in g else None
    support_settings = None
    if "second_support_tracked_node" in g.attrs and settings is not None:
        support_settings = dataclasses.replace(
            settings, tracked_node=int(attr(g, "second_support_tracked_node")))
    vertices = (get(fh, "floor/held_out_vertices", (None,), dtype="int")
                if "held_out_vertices" in g else None)

    def read_runs(name: str, runs_settings: GravitySection | None) -> GravityResult:
        if runs_settings is None:
            raise DataFileError(f"{path}:/floor/gravity or its attribute "
                                "second_support_tracked_node is missing")
        times = get(fh, f"{name}/time", (None,), dtype="float")
        _check_record_times(times, runs_settings, f"{path}:/{name}/time")
        return GravityResult(
            get(fh, f"{name}/static_displacement", (n_v, 3), dtype="float"), times,
            get(fh, f"{name}/displacement", (len(times), n_v, 3), dtype="float"),
            runs_settings)

    for element in elements:
        name = f"floor/{element}"
        e = group(fh, name)
        seconds[element] = float(attr(e, "seconds"))
        parts[element] = json_attr(e, "part_seconds", {})
        if "failed" in e.attrs:
            failed[element] = str(attr(e, "failed"))
        else:
            runs[element] = read_runs(name, settings)
        if "second_support" in e:
            if "failed" in e["second_support"].attrs:
                support_failed[element] = str(attr(e["second_support"], "failed"))
            else:
                support[element] = read_runs(f"{name}/second_support", support_settings)
        if "held_out" in e:
            if vertices is None:
                raise DataFileError(f"{path}:/floor/held_out_vertices is missing")
            held_out[element] = _read_held_out(fh, f"{name}/held_out", vertices)
    return FloorResult(runs, failed, seconds, int(attr(g, "quadrature_degree")), support,
                       support_failed, held_out, parts)


def _read_held_out(fh: h5py.File, name: str, vertices: np.ndarray) -> HeldOutCurves:
    """A floor element's held-out curves back, checked: NaN rows exactly at the failed points."""
    failed = {int(v): str(r) for v, r in json_attr(group(fh, name), "failed").items()}
    curves = {k: get(fh, f"{name}/{k}_force", (len(vertices), None, 3), finite=False,
                     dtype="float") if f"{k}_force" in fh[name] else None
              for k in ("indentation", "relaxation")}
    for k, force in curves.items():
        if force is None:
            continue
        bad = ~np.isfinite(force).all(axis=(1, 2))
        if set(vertices[bad].tolist()) != set(failed) or not np.isfinite(force[~bad]).all():
            raise DataFileError(f"{fh.filename}:/{name}/{k}_force has non-finite values at "
                                f"vertices {vertices[bad].tolist()}, its failed points are "
                                f"{sorted(failed)}")
    return HeldOutCurves(vertices, curves["indentation"], curves["relaxation"], failed)


def write_body(g: h5py.Group, body: BodyResult, n_vertices: int) -> None:
    """The ``/body`` group of ``reference.h5`` (:class:`BodyResult`)."""
    n_modes = body.frequencies.shape[1] if np.ndim(body.frequencies) == 2 else -1
    _check_shape("body.frequencies", body.frequencies, (len(BODY_MODULI), n_modes))
    _check_shape("body.shapes", body.shapes, (len(BODY_MODULI), n_modes, n_vertices, 3))
    n_loads = len(body.load_directions)
    _check_shape("body.load_directions", body.load_directions, (n_loads, 3))
    _check_shape("body.load_displacement", body.load_displacement, (n_loads, n_vertices, 3))
    g.attrs["moduli"] = json.dumps(list(BODY_MODULI))
    g.attrs["load_acceleration"] = float(body.load_acceleration)
    if body.load_failure is not None:
        if n_loads:
            raise DataFileError("body: a load failure with loads; the loads of a failed "
                                "static body load are left out")
        g.attrs["load_failure"] = body.load_failure
    put(g, "frequencies", body.frequencies, "Hz", "lowest natural frequencies, ascending, at "
        "the instantaneous (row 0) and long-term (row 1) moduli (2, M)")
    put(g, "shapes", body.shapes, "1/sqrt(kg)", "their mode shapes at the vertices, "
        "mass-normalised with the FE's consistent mass (2, M, N, 3)")
    put(g, "load_directions", body.load_directions, "1", "unit directions of the static "
        "body loads, perpendicular to the scene's gravity (L, 3)")
    put(g, "load_displacement", body.load_displacement, "m", "static displacement under "
        "each body load (weight along that direction), long-term material (L, N, 3)")
    _check_shape("body.loaded_frequencies", body.loaded_frequencies, (n_loads, n_modes))
    _check_shape("body.loaded_shapes", body.loaded_shapes, (n_loads, n_modes, n_vertices, 3))
    put(g, "loaded_frequencies", body.loaded_frequencies, "Hz", "lowest frequencies of small "
        "motions about each load's equilibrium, instantaneous incremental moduli (L, M)")
    put(g, "loaded_shapes", body.loaded_shapes, "1/sqrt(kg)", "their mode shapes at the "
        "vertices, normalised as shapes (L, M, N, 3)")
    if body.free_frequencies is not None:
        _check_shape("body.free_shapes", body.free_shapes,
                     (len(BODY_MODULI), body.free_frequencies.shape[1], n_vertices, 3))
        put(g, "free_frequencies", body.free_frequencies, "Hz", "lowest natural frequencies "
            "of the unsupported body (rigid modes left out), ascending, at the moduli of "
            "frequencies (2, M)")
        put(g, "free_shapes", body.free_shapes, "1/sqrt(kg)", "their mode shapes at the "
            "vertices, normalised as shapes (2, M, N, 3)")


def read_body(fh: h5py.File, n_vertices: int) -> BodyResult:
    """The ``/body`` group of an open ``reference.h5``, checked (:func:`write_body`)."""
    moduli = json_attr(group(fh, "body"), "moduli")
    if moduli != list(BODY_MODULI):
        raise DataFileError(f"{fh.filename}:/body attribute moduli = {moduli!r}, expected "
                            f"{list(BODY_MODULI)}")
    frequencies = get(fh, "body/frequencies", (len(BODY_MODULI), None), dtype="float")
    n_modes = frequencies.shape[1]
    directions = get(fh, "body/load_directions", (None, 3), dtype="float")
    loaded = get(fh, "body/loaded_frequencies", (len(directions), n_modes), dtype="float")
    free = free_shapes = None
    if "free_frequencies" in group(fh, "body"):  # absent from a reference computed before them
        free = get(fh, "body/free_frequencies", (len(BODY_MODULI), None), dtype="float")
        free_shapes = get(fh, "body/free_shapes",
                          (len(BODY_MODULI), free.shape[1], n_vertices, 3), dtype="float")
    for name, values in (("frequencies", frequencies), ("loaded_frequencies", loaded),
                         ("free_frequencies", free)):
        if values is None:
            continue
        if np.any(values <= 0) or np.any(np.diff(values, axis=1) < 0):
            raise DataFileError(f"{fh.filename}:/body/{name} must be positive and ascending")
    if not np.allclose(np.linalg.norm(directions, axis=1), 1.0, atol=1e-9):
        raise DataFileError(f"{fh.filename}:/body/load_directions must be unit vectors")
    acceleration = float(attr(group(fh, "body"), "load_acceleration"))
    if not acceleration > 0:
        raise DataFileError(f"{fh.filename}:/body attribute load_acceleration = "
                            f"{acceleration!r} must be > 0")
    return BodyResult(
        frequencies=frequencies,
        shapes=get(fh, "body/shapes", (len(BODY_MODULI), n_modes, n_vertices, 3), dtype="float"),
        load_directions=directions, load_acceleration=acceleration,
        load_displacement=get(fh, "body/load_displacement", (len(directions), n_vertices, 3),
                              dtype="float"),
        loaded_frequencies=loaded,
        loaded_shapes=get(fh, "body/loaded_shapes", (len(directions), n_modes, n_vertices, 3),
                          dtype="float"),
        free_frequencies=free, free_shapes=free_shapes,
        load_failure=(str(group(fh, "body").attrs["load_failure"])
                      if "load_failure" in group(fh, "body").attrs else None))



def _write_second_support(fh: h5py.File, second: SecondSupportResult, n_v: int) -> None:
    """The ``/second_support`` group (schema in the README, "HDF5 schemas")."""
    runs = second.runs
    _check_shape("second_support.static_displacement", runs.static_displacement, (n_v, 3))
    _check_shape("second_support.displacement", runs.displacement, (len(runs.time), n_v, 3))
    g = fh.create_group("second_support")
    write_section(g, second.section)
    write_section(g.create_group("gravity"), runs.settings)
    put(g, "fixed", second.fixed, "1", "ids of the vertices the second support clamps (F2,)")
    put(g, "static_displacement", runs.static_displacement, "m",
        "static sag of every vertex with the second support (N, 3)")
    put(g, "time", runs.time, "s", "release sample times, from rest at 0 (S,)")
    put(g, "displacement", runs.displacement, "m",
        "release vertex displacements with the second support (S, N, 3)")


def _read_second_support(fh: h5py.File, path: str | Path, n_v: int) -> SecondSupportResult:
    """The ``/second_support`` group back, checked: a set of vertices other than
    ``/mesh/fixed``, a free tracked node, shapes, finiteness, record times."""
    g = group(fh, "second_support")
    section = read_section(g, "second_support")
    settings = read_section(group(fh, "second_support/gravity"), "gravity")
    fixed = get(fh, "second_support/fixed", (None,), dtype="int")
    if len(fixed) == 0 or fixed.min() < 0 or fixed.max() >= n_v:
        raise DataFileError(f"{path}:/second_support/fixed does not hold vertex ids of the mesh")
    tracked = settings.tracked_node
    if not isinstance(tracked, int) or tracked in set(fixed.tolist()):
        raise DataFileError(f"{path}:/second_support/gravity tracked_node {tracked!r} is not a "
                            "free vertex of the second support")
    times = get(fh, "second_support/time", (None,), dtype="float")
    _check_record_times(times, settings, f"{path}:/second_support/time")
    runs = GravityResult(get(fh, "second_support/static_displacement", (n_v, 3), dtype="float"),
                         times, get(fh, "second_support/displacement", (len(times), n_v, 3),
                                    dtype="float"), settings)
    return SecondSupportResult(section, fixed, runs)


def _check_record_times(times: np.ndarray, settings: GravitySection, where: str) -> None:
    """DataFileError unless ``times`` are the record times of ``settings``' duration and
    record interval."""
    expected = record_times(settings.duration, settings.record_interval)
    if times.shape != expected.shape or not np.allclose(
            times, expected, rtol=1e-12, atol=1e-12 * settings.duration):
        raise DataFileError(f"{where} does not match its duration ({settings.duration} s) and "
                            f"record_interval ({settings.record_interval} s)")


def _check_shape(name: str, arr: np.ndarray, shape: tuple) -> None:
    if np.shape(arr) != shape:
        raise DataFileError(f"{name} has shape {np.shape(arr)}, expected {shape}")


def read_reference(path: str | Path, *, expect_mesh: str | None = None) -> Reference:
    """Read and check ``reference.h5``; ``expect_mesh`` is a mesh fingerprint it must match."""
    with open_h5(path, REFERENCE_KIND, REFERENCE_SCHEMA) as fh:
        problem = read_problem(fh)
        if expect_mesh is not None and problem.mesh.fingerprint() != expect_mesh:
            raise DataFileError(f"{path} was computed on a different mesh than the scene's "
                                "(mesh fingerprint mismatch); recompute the reference")
        material = read_section(group(fh, "material"), "material")
        fe = read_section(group(fh, "fe"), "fe") if "fe" in fh else None
        n_pts = len(problem.test_points)
        d = get(fh, "indentation/displacement", (None,), dtype="float")
        ind = IndentationCurves(d, get(fh, "indentation/force", (n_pts, len(d), 3), dtype="float"),
                                get(fh, "indentation/force_normal", (n_pts, len(d)),
                                    dtype="float"),
                                indenter=str(attr(group(fh, "indentation"), "indenter")),
                                # files written before the punch have no radius: a vertex's 0
                                radius=float(group(fh, "indentation").attrs.get("radius", 0.0)))
        stored = stored_experiments(fh)
        rel, t = None, None
        if "relaxation" in stored:
            t = get(fh, "relaxation/time", (None,), dtype="float")
            rel = RelaxationCurves(t, get(fh, "relaxation/displacement", (len(t),),
                                          dtype="float"),
                                   get(fh, "relaxation/force", (n_pts, len(t), 3), dtype="float"),
                                   get(fh, "relaxation/force_normal", (n_pts, len(t)),
                                       dtype="float"))
        for name, arr in (("indentation/displacement", d), ("relaxation/time", t)):
            if arr is not None and (len(arr) == 0 or np.any(np.diff(arr) <= 0) or arr[0] <= 0):
                raise DataFileError(f"{path}:/{name} must be positive and increasing")
        gravity = None
        if "gravity_static" in stored or "gravity_dynamic" in stored:
            n_v = problem.mesh.n_vertices
            settings = read_section(group(fh, "gravity"), "gravity")
            if settings.tracked_node != problem.tracked_node:
                raise DataFileError(f"{path}:/gravity tracked_node {settings.tracked_node!r} "
                                    f"differs from /test_points' {problem.tracked_node}")
            static, gt, gu = None, None, None
            if "gravity_static" in stored:
                static = get(fh, "gravity/static_displacement", (n_v, 3), dtype="float")
            if "gravity_dynamic" in stored:
                gt = get(fh, "gravity/time", (None,), dtype="float")
                _check_record_times(gt, settings, f"{path}:/gravity/time")
                gu = get(fh, "gravity/displacement", (len(gt), n_v, 3), dtype="float")
            gravity = GravityResult(static_displacement=static, time=gt, displacement=gu,
                                    settings=settings)
        body = read_body(fh, problem.mesh.n_vertices) if "body" in stored else None
        second = (_read_second_support(fh, path, problem.mesh.n_vertices)
                  if "second_support" in stored else None)
        floor = _read_floor(fh, path, problem.mesh.n_vertices) if "floor" in stored else None
        meta = {k: attr(fh, k) for k in fh.attrs}
        for name in ("fe_failures", "mesh_preflight"):  # JSON written by the FE stage
            try:
                json.loads(meta.get(name, "null"))
            except (TypeError, ValueError):
                raise DataFileError(f"{path}: attribute {name} is not JSON") from None
        FEFailures.from_json(meta.get("fe_failures"), str(path))
    return Reference(problem=problem, material=material, indentation=ind, relaxation=rel,
                     gravity=gravity, meta=meta, fe=fe, body=body, second_support=second,
                     floor=floor)


def stored_experiments(fh: h5py.File) -> tuple[str, ...]:
    """The experiments an open ``reference.h5`` holds: its ``experiments`` attribute (the four
    of :data:`~forcecal.scene.DEFAULT_EXPERIMENTS` in a file written before the attribute
    existed); DataFileError if it names an unknown experiment or a group it lists is missing."""
    if "experiments" not in fh.attrs:
        return DEFAULT_EXPERIMENTS
    raw = attr(fh, "experiments")
    try:
        listed = json.loads(raw)
    except (TypeError, ValueError):
        listed = None
    if not isinstance(listed, list) or not set(listed) <= set(EXPERIMENTS) or not listed:
        raise DataFileError(f"{fh.filename}: attribute experiments = {raw!r} is not a JSON list "
                            f"of some of {list(EXPERIMENTS)}")
    for e, where in (("indentation", "indentation"), ("relaxation", "relaxation"),
                     ("gravity_static", "gravity/static_displacement"),
                     ("gravity_dynamic", "gravity/time"), ("body", "body"),
                     ("second_support", "second_support"), ("floor", "floor")):
        if e in listed and where not in fh:
            raise DataFileError(f"{fh.filename}:/{where} is missing (the file lists {e!r} in "
                                "its experiments)")
    return tuple(e for e in EXPERIMENTS if e in listed)


#: what each experiment's results are in ``reference.h5`` (groups or datasets)
EXPERIMENT_PATHS = {"indentation": ("indentation",), "relaxation": ("relaxation",),
                    "gravity_static": ("gravity/static_displacement",),
                    "gravity_dynamic": ("gravity/time", "gravity/displacement"),
                    "body": ("body",), "second_support": ("second_support",),
                    "floor": ("floor",)}
#: what every experiment's results depend on (hashed by :func:`reference_digest` too)
SHARED_PATHS = ("mesh", "test_points", "material", "fe")


def reference_digest(path: str | Path, experiments: tuple[str, ...]) -> str:
    """SHA-256 of the content of ``reference.h5`` that ``experiments`` read: the shared
    groups (:data:`SHARED_PATHS`), the ``/gravity`` settings when a gravity experiment is
    named, and each named experiment's datasets (names, attributes, shapes, dtypes, bytes).

    A stage that reads only some experiments keys on this rather than on the whole file,
    so adding another experiment to the reference (which rewrites the file) does not
    rerun it. DataFileError if the file cannot be read or lacks a named experiment.
    """
    h = hashlib.sha256()

    def visit(name: str, obj: Any) -> None:
        h.update(name.encode() + b"\0")
        for k in sorted(obj.attrs):
            h.update(k.encode() + b"=" + repr(np.asarray(obj.attrs[k]).tolist()).encode())
        if isinstance(obj, h5py.Dataset):
            data = np.ascontiguousarray(obj[()])
            h.update(f"{data.dtype.str}{data.shape}".encode() + data.tobytes())

    with open_h5(path, REFERENCE_KIND, REFERENCE_SCHEMA) as fh:
        stored = stored_experiments(fh)
        missing = [e for e in experiments if e not in stored]
        if missing:
            raise DataFileError(f"{path} has no {missing} results (it holds {list(stored)})")
        names = list(SHARED_PATHS) + [p for e in EXPERIMENTS if e in experiments
                                      for p in EXPERIMENT_PATHS[e]]
        try:
            if any(e.startswith("gravity") for e in experiments):
                visit("gravity", fh["gravity"])  # its attributes: the settings
            for name in names:
                if name not in fh:
                    continue
                obj = fh[name]
                visit(name, obj)
                if isinstance(obj, h5py.Group):
                    obj.visititems(lambda sub, o, name=name: visit(f"{name}/{sub}", o))
        except (OSError, KeyError, RuntimeError) as exc:
            raise DataFileError(f"{path} cannot be read to fingerprint it (corrupt file?): "
                                f"{exc}") from exc
    return h.hexdigest()
