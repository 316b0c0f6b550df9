"""The calibration's result and its file, ``params.h5`` (kind ``forcecal.params``).

Schema (every dataset has a ``unit`` attribute; P test points = Pc calibration
points then the held-out ones, E connectors in ``mesh/edges`` order):

| path | shape | unit | content |
|---|---|---|---|
| ``/`` attrs | | | ``kind``, ``schema_version``, ``forcecal_version``, ``created``, ``reference_fingerprint`` (SHA-256 of the reference's content the fit read, :func:`forcecal.h5io.reference_digest`), ``reference_path``, ``wall_time`` [s], ``settings`` (JSON: section -> table, the scene sections the fit read: ``mesh``, ``material``, ``fixed``, ``test_points``, ``indentation``, ``relaxation``, ``calibration``; and ``model``: ``{"particle.volume": bool}``, the model fitted, with ``"particle.volume_element": "nodal"`` for the nodal volume element (absent: per tet)), ``versions`` (JSON: python, numpy, scipy, numba, h5py, mpi4py (null if not installed), forcecal, git_commit (``git rev-parse HEAD``, ``+dirty`` if tracked files differ; null outside a git checkout)), ``gradient`` (JSON: the gradient method's smoothness weight, CV costs and objective history; ``{}`` for the paper's method), ``experiments`` (JSON list: ``indentation`` and, if fitted, ``relaxation``; absent = both), ``body`` (JSON, with the experiment ``body``: ``status`` = ``"fitted"``, ``"failed"`` (the calibrated model does not carry a whole-body load it was fitted to, or has no modes: a failed calibration; ``failure`` says why) or ``"not fitted"``; ``kinds`` fitted, ``weight``, ``failure``, and ``variants``: each variant's whole-body errors (``items``, ``item_errors``, ``load_errors``, per modulus ``frequency_errors``, ``shape_errors``, ``mac``, ``partner``) or ``{"failure": reason}``, :func:`calibration.body.body_record`; ``{}`` or absent: no whole-body data) |
| ``/mesh``, ``/test_points`` | | | as in ``reference.h5`` (:func:`forcecal.h5io.write_problem`) |
| ``/connectors/<variant>/<name>`` | (E,) | N/m, N s/m | ``K0, a, b, k1, b1, k2, b2`` per connector; variants ``baseline`` (Van Gelder), ``global`` (uniform), ``calibrated`` (global + local, or the gradient fit) |
| ``/connectors/<variant>/kv`` | (T,) or (1,) | Pa | volume stiffness per tet ((1,): the same for every tet); only when the volume term is on (``particle.volume``) |
| ``/connectors/<variant>/<name>`` | (T,) or (1,) | Pa, Pa s | ``kv1, bv1, kv2, bv2``: the volume term's Maxwell arms per tet, shaped as ``kv``; only when it relaxes (``particle.volume = "viscoelastic"``) |
| ``/global/<name>``, ``/initial_guess/<name>`` | () | N/m, 1, s, Pa | ``K0, alpha, beta, k1, tau1, k2, tau2, kv, kv1, kv2`` (``a = alpha K0``, ``b = beta K0``, ``b_i = tau_i k_i``; ``kv`` = 0: no volume term, absent in older files; ``kv1, kv2``: the volume arms' stiffnesses, their times ``tau1, tau2``, 0: an elastic volume term, absent in older files) |
| ``/initial_guess/fe_slope`` | (Pc,) | N/m | FE initial static slope per calibration point |
| ``/initial_guess/unit_slope`` | (P,) | N/m | unit-stiffness network slope per test point |
| ``/strain_range`` attrs | | 1 | ``low``, ``high``: where K(eps) > 0 is required |
| ``/local/z_static``, ``/local/z_relaxation`` | (Pc, 3), (Pc, 4) | 1 | ring offsets (see :mod:`calibration.parametrisation`) |
| ``/errors/<variant>/<experiment>`` | (P,) | 1 | relative RMS error per test point; experiments ``indentation``, ``relaxation`` (those fitted); NaN at a point the variant failed |
| ``/curves/<variant>/<experiment>`` | (P, S) | N | simulated normal-force curves at the reference's samples; a row of NaN at a point the variant failed (recorded in ``failures``) |
| ``/forces/<variant>/<experiment>`` | (P, S, 3) | N | the simulated indenter force vectors whose inward-normal components the curves are (absent in files written before them); NaN rows as the curves |
| ``/strains/<variant>/<experiment>`` | (P, 2) | 1 | the smallest and the largest connector strain over every sample of each point's curve: where the variant's spring laws were evaluated (absent in files written before them); NaN rows as the curves |
| ``/history/global_<phase>/`` | | | ``evaluation_cost`` (n,) N^2, ``iteration_cost`` (m,) N^2, ``iteration_evaluations`` (m,); attrs ``x``, ``cost``, ``initial_cost``, ``converged``, ``warnings`` (JSON); phases ``static``, ``relaxation`` |
| ``/history/local_<phase>/sweep_<k>/`` | | | attrs ``start_cost``, ``end_cost`` [N^2], ``halvings`` (-1 = rejected); per point: ``x`` (Pc, d), ``cost``, ``initial_cost`` (Pc,), ``converged`` (Pc,), ``evaluation_cost`` (all points concatenated) with ``evaluation_offsets`` (Pc+1,), ``iteration_cost``/``iteration_evaluations`` with ``iteration_offsets`` (Pc+1,); attr ``warnings`` (JSON list per point) |
| ``/evaluations`` attrs | | | point-curve and cost-function evaluation counts per phase |
| ``/stage_times`` attrs | | s | wall time this run spent on each phase (a phase loaded from a checkpoint: the time to load it, about 0; a phase resumed part-way: the rest of its work) |
| ``/warnings`` | (n,) | | every warning of the run (strings) |
| ``/`` attr ``failures`` | | | JSON list of the validation failures: a variant that did not complete an experiment at a test point (:class:`calibration.validation.ValidationFailure` records: ``model`` (the variant), ``experiment``, ``point`` (vertex id), ``role`` (``calibration`` / ``held_out``), ``reached`` (``{"depth_m": ...}`` or ``{"time_s": ...}``), ``reason``); absent in files written before it: none. Its rows are the only non-finite values of the file |
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from calibration.local import Sweep
from calibration.optimize import Fit, History
from calibration.parametrisation import GlobalParams, StrainRange
from calibration.validation import (ValidationFailure, check_failed_rows, failures_json,
                                    parse_failures)
from forcecal.errors import DataFileError
from forcecal.h5io import (atomic_h5, attr, get, json_attr, open_h5, put, read_problem,
                           write_problem)
from forcecal.problem import Problem
from particle.params import PARAM_NAMES, VOLUME_ARM_NAMES, ConnectorParams

PARAMS_KIND = "forcecal.params"
PARAMS_SCHEMA = 1
VARIANTS = ("baseline", "global", "calibrated")
EXPERIMENTS = ("indentation", "relaxation")
PHASES = ("static", "relaxation")
PARAM_UNITS = {"K0": "N/m", "a": "N/m", "b": "N/m", "k1": "N/m", "b1": "N s/m", "k2": "N/m",
               "b2": "N s/m"}
GLOBAL_UNITS = {"K0": "N/m", "alpha": "1", "beta": "1", "k1": "N/m", "tau1": "s", "k2": "N/m",
                "tau2": "s", "kv": "Pa", "kv1": "Pa", "kv2": "Pa"}
#: the volume term's per-tet arrays of ``/connectors/<variant>/`` (besides ``kv``)
VOLUME_ARM_UNITS = {"kv1": "Pa", "bv1": "Pa s", "kv2": "Pa", "bv2": "Pa s"}


@dataclass(frozen=True, eq=False)
class VariantCurves:
    """Simulated curves and errors of one model variant at every test point.

    Attributes:
        curves: experiment -> (P, S) float64 normal forces [N].
        errors: experiment -> (P,) float64 relative RMS errors [1].
        forces: experiment -> (P, S, 3) float64 force vectors [N] whose inward-normal
            components ``curves`` are; None when read from a file written before them.
        strains: experiment -> (P, 2) float64, the smallest and largest connector strain [1]
            over each point's curve; None when read from a file written before them.
    """
    curves: dict[str, np.ndarray]
    errors: dict[str, np.ndarray]
    forces: dict[str, np.ndarray] | None = None
    strains: dict[str, np.ndarray] | None = None


@dataclass(frozen=True, eq=False)
class CalibrationResult:
    """Everything a calibration produced (and ``params.h5`` holds).

    Attributes:
        problem: mesh, fixed nodes and test points.
        initial: closed-form initial guess.
        global_params: result of global tuning.
        connectors: variant -> per-connector parameters (``baseline``, ``global``, ``calibrated``).
        variants: variant -> curves and errors at every test point.
        z_static: (Pc, 3) static ring offsets; z_relaxation: (Pc, 4) relaxation ring offsets.
        strain: strain range on which K(eps) > 0 was required.
        fe_slope: (Pc,) FE initial static slopes [N/m]; unit_slope: (P,) unit-network slopes [N/m].
        global_fits: phase -> Nelder-Mead result of the global phase.
        local_sweeps: phase -> Jacobi sweeps (empty when local tuning is off).
        settings: section -> table of the scene sections the fit read.
        reference_fingerprint: SHA-256 of the reference file fitted to.
        reference_path: its path.
        evaluations: evaluation counts (see :func:`write_params`).
        stage_times: phase -> wall time this run spent on it [s] (about 0 for a phase loaded
            from a checkpoint, the remaining work for one resumed part-way).
        wall_time: wall-clock time of the calibration [s].
        warnings: every warning of the run.
        versions: software versions and the git commit (None outside a checkout).
        experiments: the experiments fitted and evaluated (``variants`` hold their curves
            and errors only); without ``relaxation`` the arms are not calibrated.
        gradient: the gradient method's summary (smoothness weight, CV costs, objective
            history; empty for the paper's method).
        body: the whole-body record (:func:`calibration.body.body_record`; empty without
            the experiment ``body``).
        failures: the validation failures: a variant that did not complete an experiment at
            a test point (its rows of ``variants`` are NaN there).
    """
    problem: Problem
    initial: GlobalParams
    global_params: GlobalParams
    connectors: dict[str, ConnectorParams]
    variants: dict[str, VariantCurves]
    z_static: np.ndarray
    z_relaxation: np.ndarray
    strain: StrainRange
    fe_slope: np.ndarray
    unit_slope: np.ndarray
    global_fits: dict[str, Fit]
    local_sweeps: dict[str, list[Sweep]]
    settings: dict
    reference_fingerprint: str
    reference_path: str
    evaluations: dict[str, int]
    stage_times: dict[str, float]
    wall_time: float
    warnings: tuple[str, ...] = field(default=())
    versions: dict[str, str | None] = field(default_factory=dict)
    experiments: tuple[str, ...] = EXPERIMENTS
    gradient: dict = field(default_factory=dict)
    body: dict = field(default_factory=dict)
    failures: tuple[ValidationFailure, ...] = ()

    @property
    def is_calibration(self) -> np.ndarray:
        """(P,) bool: True for calibration points, False for held-out ones."""
        n = len(self.problem.calibration)
        return np.arange(len(self.problem.test_points)) < n

    def error_summary(self) -> dict[str, dict[str, dict[str, float]]]:
        """variant -> experiment -> {"calibration_mean", "calibration_max", "held_out_mean",
        "held_out_max"} relative RMS errors [1] over the points the variant completed (keys
        absent without such points)."""
        out: dict = {}
        for v, vc in self.variants.items():
            out[v] = {}
            for e, err in vc.errors.items():
                row = {}
                for group, mask in (("calibration", self.is_calibration),
                                    ("held_out", ~self.is_calibration)):
                    mask = mask & np.isfinite(err)
                    if mask.any():
                        row[f"{group}_mean"] = float(err[mask].mean())
                        row[f"{group}_max"] = float(err[mask].max())
                out[v][e] = row
        return out

    def summary(self) -> str:
        """Human-readable table of the errors and the run's figures."""
        g = self.global_params
        lines = [f"calibration of {len(self.problem.mesh.edges)} connectors on "
                 f"{len(self.problem.calibration)} calibration + {len(self.problem.held_out)} "
                 f"held-out points: {self.wall_time:.1f} s, "
                 f"{self.evaluations.get('point_curves', 0)} point-curve evaluations ("
                 + ", ".join(f"{k} {v:.1f} s" for k, v in self.stage_times.items()) + ")",
                 f"global: K0 = {g.K0:.4g} N/m, alpha = {g.alpha:.4g}, beta = {g.beta:.4g}, "
                 f"k1 = {g.k1:.4g} N/m, tau1 = {g.tau1:.4g} s, k2 = {g.k2:.4g} N/m, "
                 f"tau2 = {g.tau2:.4g} s",
                 "relative RMS error, mean / max [%]:",
                 f"{'variant':<11} {'experiment':<12} {'calibration':>17} {'held-out':>17}"]
        for v, exps in self.error_summary().items():
            for e, row in exps.items():
                cells = [f"{100 * row[f'{grp}_mean']:7.2f} / {100 * row[f'{grp}_max']:6.2f}"
                         if f"{grp}_mean" in row else f"{'-':>16}"
                         for grp in ("calibration", "held_out")]
                lines.append(f"{v:<11} {e:<12} {cells[0]:>17} {cells[1]:>17}")
        lines += [f"warning: {w}" for w in self.warnings]
        lines += [f"failed: {f.describe()}" for f in self.failures]
        return "\n".join(lines)


def _put_global(group: h5py.Group, g: GlobalParams) -> None:
    for k, v in g.as_dict().items():
        put(group, k, v, GLOBAL_UNITS[k])


def _get_global(fh: h5py.File, path: str) -> GlobalParams:
    # kv (kv1, kv2) is absent from files written before the volume term (its arms): 0
    return GlobalParams(**{k: float(get(fh, f"{path}/{k}", ())) for k in GLOBAL_UNITS
                           if k not in ("kv", "kv1", "kv2") or f"{path}/{k}" in fh})


def _put_history(group: h5py.Group, fit: Fit) -> None:
    h = fit.history
    put(group, "evaluation_cost", h.evaluation_cost, "N^2", "cost of every evaluation")
    put(group, "iteration_cost", h.iteration_cost, "N^2", "best cost after each iteration")
    put(group, "iteration_evaluations", h.iteration_evaluations, "1",
        "evaluations done by the end of each iteration")
    group.attrs["x"] = fit.x
    group.attrs["cost"] = fit.cost
    group.attrs["initial_cost"] = fit.initial_cost
    group.attrs["converged"] = fit.converged
    group.attrs["warnings"] = json.dumps(list(fit.warnings))


def _get_fit(fh: h5py.File, path: str) -> Fit:
    g = fh[path]
    history = History(get(fh, f"{path}/evaluation_cost", (None,), finite=False, dtype="float"),
                      get(fh, f"{path}/iteration_cost", (None,), dtype="float"),
                      get(fh, f"{path}/iteration_evaluations", (None,), dtype="int"))
    return Fit(np.asarray(attr(g, "x"), dtype=float), float(attr(g, "cost")),
               float(attr(g, "initial_cost")), bool(attr(g, "converged")), history,
               tuple(json_attr(g, "warnings")))


def _ragged(group: h5py.Group, name: str, arrays: list[np.ndarray], unit: str, doc: str) -> None:
    put(group, name, np.concatenate(arrays) if arrays else np.zeros(0), unit, doc)
    put(group, f"{name.split('_')[0]}_offsets", np.cumsum([0] + [len(a) for a in arrays]), "1",
        f"point j's entries of {name} are [offsets[j], offsets[j+1])")


def _put_sweep(group: h5py.Group, sweep: Sweep) -> None:
    group.attrs["start_cost"] = sweep.start_cost
    group.attrs["end_cost"] = sweep.end_cost
    group.attrs["halvings"] = sweep.halvings
    fits = sweep.fits
    put(group, "x", np.array([f.x for f in fits]), "1", "fitted offsets per point (Pc, d)")
    put(group, "cost", [f.cost for f in fits], "N^2", "final cost per point")
    put(group, "initial_cost", [f.initial_cost for f in fits], "N^2", "starting cost per point")
    put(group, "converged", [f.converged for f in fits], "1", "tolerances met per point")
    _ragged(group, "evaluation_cost", [f.history.evaluation_cost for f in fits], "N^2",
            "cost of every evaluation, points concatenated")
    _ragged(group, "iteration_cost", [f.history.iteration_cost for f in fits], "N^2",
            "best cost after each iteration, points concatenated")
    put(group, "iteration_evaluations",
        np.concatenate([f.history.iteration_evaluations for f in fits]).astype(np.int64), "1",
        "evaluations done by the end of each iteration, points concatenated")
    group.attrs["warnings"] = json.dumps([list(f.warnings) for f in fits])


def _get_sweep(fh: h5py.File, path: str) -> Sweep:
    g = fh[path]
    x = get(fh, f"{path}/x", (None, None), dtype="float")
    n = len(x)
    cost = get(fh, f"{path}/cost", (n,), dtype="float")
    initial = get(fh, f"{path}/initial_cost", (n,), dtype="float")
    converged = get(fh, f"{path}/converged", (n,)).astype(bool)
    ev = get(fh, f"{path}/evaluation_cost", (None,), finite=False, dtype="float")
    ev_off = get(fh, f"{path}/evaluation_offsets", (n + 1,), dtype="int")
    it = get(fh, f"{path}/iteration_cost", (None,), dtype="float")
    it_n = get(fh, f"{path}/iteration_evaluations", (len(it),), dtype="int")
    it_off = get(fh, f"{path}/iteration_offsets", (n + 1,), dtype="int")
    warnings = json_attr(g, "warnings")
    fits = tuple(Fit(x[j], float(cost[j]), float(initial[j]), bool(converged[j]),
                     History(ev[ev_off[j]:ev_off[j + 1]], it[it_off[j]:it_off[j + 1]],
                             it_n[it_off[j]:it_off[j + 1]]), tuple(warnings[j]))
                 for j in range(n))
    return Sweep(float(attr(g, "start_cost")), float(attr(g, "end_cost")),
                 int(attr(g, "halvings")), fits)


def write_params(path: str | Path, result: CalibrationResult) -> None:
    """Write ``params.h5`` atomically (schema in the module docstring)."""
    with atomic_h5(path, PARAMS_KIND, PARAMS_SCHEMA) as fh:
        fh.attrs["reference_fingerprint"] = result.reference_fingerprint
        fh.attrs["reference_path"] = result.reference_path
        fh.attrs["wall_time"] = result.wall_time
        fh.attrs["settings"] = json.dumps(result.settings)
        fh.attrs["versions"] = json.dumps(result.versions)
        fh.attrs["experiments"] = json.dumps(list(result.experiments))
        fh.attrs["gradient"] = json.dumps(result.gradient)
        fh.attrs["body"] = json.dumps(result.body)
        fh.attrs["failures"] = failures_json(result.failures)
        write_problem(fh, result.problem)
        for variant, params in result.connectors.items():
            g = fh.create_group(f"connectors/{variant}")
            for name in PARAM_NAMES:
                put(g, name, getattr(params, name), PARAM_UNITS[name])
            if params.kv is not None:
                put(g, "kv", params.kv, "Pa", "volume stiffness: one per tet, or (1,) for all")
            if params.has_volume_arms:
                for name in VOLUME_ARM_NAMES:
                    put(g, name, getattr(params, name), VOLUME_ARM_UNITS[name],
                        "the volume term's Maxwell arms, shaped as kv")
        _put_global(fh.create_group("global"), result.global_params)
        g = fh.create_group("initial_guess")
        _put_global(g, result.initial)
        put(g, "fe_slope", result.fe_slope, "N/m", "FE initial static slope per calibration point")
        put(g, "unit_slope", result.unit_slope, "N/m", "unit-stiffness network slope per point")
        s = fh.create_group("strain_range")
        s.attrs["low"], s.attrs["high"] = result.strain.low, result.strain.high
        g = fh.create_group("local")
        put(g, "z_static", result.z_static, "1", "static ring offsets (Pc, 3)")
        put(g, "z_relaxation", result.z_relaxation, "1", "relaxation ring offsets (Pc, 4)")
        for variant, vc in result.variants.items():
            for e in result.experiments:
                put(fh, f"errors/{variant}/{e}", vc.errors[e], "1", "relative RMS error (P,)")
                put(fh, f"curves/{variant}/{e}", vc.curves[e], "N", "normal-force curves (P, S)")
                if vc.forces is not None:
                    put(fh, f"forces/{variant}/{e}", vc.forces[e], "N",
                        "indenter force vectors (P, S, 3)")
                if vc.strains is not None:
                    put(fh, f"strains/{variant}/{e}", vc.strains[e], "1",
                        "smallest and largest connector strain over each curve (P, 2)")
        for phase, fit in result.global_fits.items():
            _put_history(fh.create_group(f"history/global_{phase}"), fit)
        for phase, sweeps in result.local_sweeps.items():
            g = fh.create_group(f"history/local_{phase}")
            for k, sweep in enumerate(sweeps):
                _put_sweep(g.create_group(f"sweep_{k:02d}"), sweep)
        for name in ("evaluations", "stage_times"):
            g = fh.create_group(name, track_order=True)  # attributes read back in phase order
            for k, v in getattr(result, name).items():
                g.attrs[k] = v
        fh.create_dataset("warnings", data=np.array(result.warnings, dtype=object),
                          dtype=h5py.string_dtype())


def read_params(path: str | Path) -> CalibrationResult:
    """Read ``params.h5`` back (checks kind, schema, shapes and finiteness)."""
    with open_h5(path, PARAMS_KIND, PARAMS_SCHEMA) as fh:
        problem = read_problem(fh)
        n_e, n_p, n_c = len(problem.mesh.edges), len(problem.test_points), len(problem.calibration)
        # a file without the attribute predates optional experiments: it has both
        fitted = tuple(json_attr(fh, "experiments", EXPERIMENTS))
        if not set(fitted) <= set(EXPERIMENTS) or "indentation" not in fitted:
            raise DataFileError(f"{path}: attribute experiments = {list(fitted)} is not "
                                f"'indentation' and maybe 'relaxation'")
        connectors = {v: ConnectorParams(
            **{n: get(fh, f"connectors/{v}/{n}", (n_e,), dtype="float") for n in PARAM_NAMES},
            **{n: (get(fh, f"connectors/{v}/{n}", (None,), dtype="float")
                   if f"connectors/{v}/{n}" in fh else None)
               for n in ("kv",) + VOLUME_ARM_NAMES})
            for v in VARIANTS}
        failures = parse_failures(json_attr(fh, "failures", []), f"{path}: failures")
        variants = {v: _read_variant(fh, v, fitted, problem.test_points, failures)
                    for v in VARIANTS}
        local_sweeps = {}
        for phase in PHASES:
            group = f"history/local_{phase}"
            names = sorted(fh[group]) if group in fh else []
            local_sweeps[phase] = [_get_sweep(fh, f"{group}/{s}") for s in names]
        return CalibrationResult(
            problem=problem, initial=_get_global(fh, "initial_guess"),
            global_params=_get_global(fh, "global"), connectors=connectors, variants=variants,
            z_static=get(fh, "local/z_static", (n_c, 3), dtype="float"),
            z_relaxation=get(fh, "local/z_relaxation", (n_c, 4), dtype="float"),
            strain=StrainRange(float(attr(fh["strain_range"], "low")),
                               float(attr(fh["strain_range"], "high"))),
            fe_slope=get(fh, "initial_guess/fe_slope", (n_c,), dtype="float"),
            unit_slope=get(fh, "initial_guess/unit_slope", (n_p,), dtype="float"),
            global_fits={s: _get_fit(fh, f"history/global_{s}") for s in PHASES
                         if f"history/global_{s}" in fh},
            local_sweeps=local_sweeps, settings=json_attr(fh, "settings"),
            reference_fingerprint=str(attr(fh, "reference_fingerprint")),
            reference_path=str(attr(fh, "reference_path")),
            evaluations={k: int(v) for k, v in fh["evaluations"].attrs.items()},
            stage_times={k: float(v) for k, v in fh["stage_times"].attrs.items()},
            wall_time=float(attr(fh, "wall_time")),
            warnings=tuple(s.decode() if isinstance(s, bytes) else str(s)
                           for s in fh["warnings"][()]),
            versions=json_attr(fh, "versions"), experiments=fitted,
            gradient=json_attr(fh, "gradient", {}), body=json_attr(fh, "body", {}),
            failures=failures)


def _read_variant(fh: h5py.File, variant: str, fitted: tuple[str, ...], points: np.ndarray,
                  failures: tuple[ValidationFailure, ...]) -> VariantCurves:
    """One variant's curves, errors and force vectors: NaN only in the rows of the test
    ``points`` (vertex ids) it failed (``failures``)."""
    n_points = len(points)
    index = {int(p): k for k, p in enumerate(points)}

    def read(kind: str, e: str, shape: tuple) -> np.ndarray:
        failed = [index.get(f.point, -1) for f in failures
                  if f.model == variant and f.experiment == e]
        if -1 in failed:
            raise DataFileError(f"{fh.filename}: a failure names a point that is not a test "
                                "point")
        name = f"{kind}/{variant}/{e}"
        return check_failed_rows(get(fh, name, shape, finite=False, dtype="float"), failed,
                                 f"{fh.filename}:/{name}")

    return VariantCurves(
        curves={e: read("curves", e, (n_points, None)) for e in fitted},
        errors={e: read("errors", e, (n_points,)) for e in fitted},
        forces=({e: read("forces", e, (n_points, None, 3)) for e in fitted}
                if f"forces/{variant}" in fh else None),
        strains=({e: read("strains", e, (n_points, 2)) for e in fitted}
                 if f"strains/{variant}" in fh else None))
