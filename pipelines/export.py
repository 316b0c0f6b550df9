"""Export of a calibrated model for other tools: VTU for ParaView, JSON for another engine.

``python -m pipelines export --params runs/<scene>/params.h5 --out DIR`` writes into DIR
(schema and units: ``docs/export.md``):

* ``connectors.vtu``: the particles as points (``mass_kg``, ``fixed``) and the connectors as
  line cells with each connector's parameters as cell data (``K0_N_per_m``, ``a_N_per_m``,
  ``b_N_per_m``, ``k1_N_per_m``, ``tau1_s``, ``k2_N_per_m``, ``tau2_s``, ``rest_length_m``);
* ``tets.vtu``: the tetrahedra (``rest_volume_m3``) and, when the model has the volume term,
  each tet's ``kv_Pa`` (and its arms' ``kv1_Pa``, ``tau_v1_s``, ``kv2_Pa``, ``tau_v2_s``);
* ``model.json`` (format :data:`EXPORT_FORMAT`, schema :data:`EXPORT_SCHEMA`): everything an
  engine needs to run the model (positions, masses, fixed particles, connectors, rest lengths
  and volumes, per-connector and per-tet parameters) and the explicit step the rigorous
  stability bound allows. :func:`read_model_json` rebuilds the :class:`~particle.model.Model`
  from it, with exactly the numbers of the model it was written from (JSON keeps every
  float64 exactly).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Callable

import numpy as np

from calibration.loading import CalibratedModel
from forcecal import __version__
from forcecal.errors import DataFileError, ForcecalError
from forcecal.h5io import atomic_path
from forcecal.scene import ParticleSection
from particle.nodal_volume import refuse_nodal
from particle.haptics import substeps_per_period
from particle.model import Model
from particle.params import PARAM_NAMES, VOLUME_ARM_NAMES, ConnectorParams, StrainBounds
from particle.stability import critical_time_step
from pipelines.realtime import PERIOD, session_strain_range

EXPORT_FORMAT = "forcecal.particle_model"
EXPORT_SCHEMA = 1
CONNECTORS_VTU = "connectors.vtu"
TETS_VTU = "tets.vtu"
MODEL_JSON = "model.json"
#: fraction of the stability limit the recommended step takes (the scene default)
DT_SAFETY = ParticleSection().dt_safety

#: cell data of ``connectors.vtu``: field name (unit in the name) -> its (E,) values
CONNECTOR_FIELDS: dict[str, Callable[[Model], np.ndarray]] = {
    "K0_N_per_m": lambda m: m.params.K0, "a_N_per_m": lambda m: m.params.a,
    "b_N_per_m": lambda m: m.params.b, "k1_N_per_m": lambda m: m.params.k1,
    "tau1_s": lambda m: m.params.tau1, "k2_N_per_m": lambda m: m.params.k2,
    "tau2_s": lambda m: m.params.tau2, "rest_length_m": lambda m: m.rest_lengths}
#: cell data of ``tets.vtu`` with the volume term (``kv``), and with its arms
VOLUME_FIELDS: dict[str, Callable[[ConnectorParams], np.ndarray]] = {
    "kv_Pa": lambda p: p.kv}
VOLUME_ARM_FIELDS: dict[str, Callable[[ConnectorParams], np.ndarray]] = {
    "kv1_Pa": lambda p: p.kv1, "tau_v1_s": lambda p: p.volume_arm_tau[:, 0],
    "kv2_Pa": lambda p: p.kv2, "tau_v2_s": lambda p: p.volume_arm_tau[:, 1]}
#: units of ``model.json``'s arrays and numbers (written into the file as ``units``)
JSON_UNITS = {"positions": "m", "masses": "kg", "rest_lengths": "m", "rest_volumes": "m^3",
              "K0": "N/m", "a": "N/m", "b": "N/m", "k1": "N/m", "b1": "N s/m", "k2": "N/m",
              "b2": "N s/m", "kv": "Pa", "kv1": "Pa", "bv1": "Pa s", "kv2": "Pa",
              "bv2": "Pa s", "strain": "1", "time": "s"}


def _point_data(model: Model) -> dict[str, np.ndarray]:
    return {"mass_kg": model.masses, "fixed": model.fixed.astype(np.int8)}


def connectors_mesh(model: Model):
    """``connectors.vtu``'s content: the connectors as line cells with their parameters."""
    import meshio

    return meshio.Mesh(model.rest_positions, [("line", model.edges)],
                       point_data=_point_data(model),
                       cell_data={name: [np.asarray(f(model), dtype=np.float64)]
                                  for name, f in CONNECTOR_FIELDS.items()})


def tets_mesh(model: Model):
    """``tets.vtu``'s content: the tets with their rest volumes and volume term."""
    import meshio

    fields = {"rest_volume_m3": model.rest_volumes}
    p = model.params
    if p.kv is not None:
        fields.update({n: f(p) for n, f in VOLUME_FIELDS.items()})
    if p.has_volume_arms:
        fields.update({n: f(p) for n, f in VOLUME_ARM_FIELDS.items()})
    return meshio.Mesh(model.rest_positions, [("tetra", model.tets)],
                       point_data=_point_data(model),
                       cell_data={n: [np.asarray(v, dtype=np.float64)] for n, v in fields.items()})


def time_step(model: Model, strain_range: StrainBounds, safety: float = DT_SAFETY
              ) -> dict[str, Any]:
    """``model.json``'s ``time_step``: the stability limit [s] of the explicit step over
    ``strain_range`` (per connector), the step ``safety`` x it, and the substeps of a 1 ms
    haptic period at that step."""
    critical = critical_time_step(model, strain_range=strain_range)
    dt = safety * critical
    lo, hi = (np.broadcast_to(np.asarray(b, dtype=np.float64), (model.n_connectors,))
              for b in strain_range)
    return {"critical_dt": critical if math.isfinite(critical) else None,
            "dt": dt if math.isfinite(dt) else None, "dt_safety": safety,
            "period": PERIOD,
            "substeps_per_period": substeps_per_period(PERIOD, dt)
            if math.isfinite(dt) else 1,
            "strain_low": lo.tolist(), "strain_high": hi.tolist()}


def model_document(calibrated: CalibratedModel) -> dict[str, Any]:
    """``model.json``'s content (schema: ``docs/export.md``)."""
    model = calibrated.model
    refuse_nodal(model, "the export (model.json)")
    p = model.params
    volume = None
    if p.kv is not None:
        volume = {"kv": p.kv.tolist(), **{n: (getattr(p, n).tolist() if p.has_volume_arms
                                              else None) for n in VOLUME_ARM_NAMES}}
    return {
        "format": EXPORT_FORMAT, "schema_version": EXPORT_SCHEMA,
        "forcecal_version": __version__, "source": calibrated.source,
        "variant": calibrated.variant, "units": JSON_UNITS,
        "density": calibrated.density,
        "n_particles": model.n_particles, "n_connectors": model.n_connectors,
        "n_tets": model.n_tets,
        "positions": model.rest_positions.tolist(), "masses": model.masses.tolist(),
        "fixed": np.nonzero(model.fixed)[0].tolist(),
        "edges": model.edges.tolist(), "rest_lengths": model.rest_lengths.tolist(),
        "connectors": {n: getattr(p, n).tolist() for n in PARAM_NAMES},
        "tets": model.tets.tolist(), "rest_volumes": model.rest_volumes.tolist(),
        "volume": volume,
        "valid_strain": {"low": calibrated.strain_range[0],
                         "high": calibrated.strain_range[1]},
        "time_step": time_step(model, session_strain_range(p))}


def export_model(calibrated: CalibratedModel, out: str | Path) -> list[Path]:
    """Write ``connectors.vtu``, ``tets.vtu`` and ``model.json`` into ``out`` (each
    atomically); returns their paths."""
    out = Path(out)
    written = []
    for name, mesh in ((CONNECTORS_VTU, connectors_mesh(calibrated.model)),
                       (TETS_VTU, tets_mesh(calibrated.model))):
        with atomic_path(out / name) as tmp:
            mesh.write(tmp, file_format="vtu")
        written.append(out / name)
    document = model_document(calibrated)
    with atomic_path(out / MODEL_JSON) as tmp:
        tmp.write_text(json.dumps(document) + "\n")
    written.append(out / MODEL_JSON)
    return written


def model_from_document(document: dict[str, Any], where: str = "model.json") -> Model:
    """The :class:`Model` a ``model.json`` document describes; :class:`DataFileError` naming
    the problem when it is not one."""
    if not isinstance(document, dict) or document.get("format") != EXPORT_FORMAT:
        raise DataFileError(f"{where} is not a {EXPORT_FORMAT} file")
    if document.get("schema_version") != EXPORT_SCHEMA:
        raise DataFileError(f"{where} has schema version {document.get('schema_version')!r}, "
                            f"this code reads {EXPORT_SCHEMA}")
    try:
        volume = document["volume"] or {}
        params = ConnectorParams(**{n: np.asarray(document["connectors"][n], dtype=np.float64)
                                    for n in PARAM_NAMES},
                                 **{n: (None if volume.get(n) is None
                                        else np.asarray(volume[n], dtype=np.float64))
                                    for n in ("kv",) + VOLUME_ARM_NAMES})
        positions = np.asarray(document["positions"], dtype=np.float64).reshape(-1, 3)
        n = len(positions)
        edges = _ids(document["edges"], n, 2, "edges", where)
        tets = _ids(document["tets"], n, 4, "tets", where)
        fixed = np.zeros(n, dtype=bool)
        fixed[_ids(document["fixed"], n, 1, "fixed", where)] = True
        arrays = {name: np.asarray(document[name], dtype=np.float64)
                  for name in ("masses", "rest_lengths", "rest_volumes")}
        for name, count in (("masses", n), ("rest_lengths", len(edges)),
                            ("rest_volumes", len(tets))):
            if arrays[name].shape != (count,):
                raise DataFileError(f"{where}: {name} has shape {arrays[name].shape}, "
                                    f"expected ({count},)")
        return Model(rest_positions=positions, edges=edges, rest_lengths=arrays["rest_lengths"],
                     masses=arrays["masses"], fixed=fixed, params=params, tets=tets,
                     rest_volumes=arrays["rest_volumes"])
    except KeyError as exc:
        raise DataFileError(f"{where}: {exc} is missing") from None
    except DataFileError:
        raise
    except (TypeError, ValueError, ForcecalError) as exc:
        raise DataFileError(f"{where}: not a valid model: {exc}") from None


def _ids(values, n: int, columns: int, name: str, where: str) -> np.ndarray:
    """``values`` as an (k, columns) int64 array of particle ids (k, for one column) in
    0..n-1, else :class:`DataFileError`."""
    ids = np.asarray(values, dtype=np.int64).reshape(-1, columns)
    if ids.size and (ids.min() < 0 or ids.max() >= n):
        raise DataFileError(f"{where}: {name} name particles outside 0..{n - 1}")
    return ids[:, 0] if columns == 1 else ids


def read_model_json(path: str | Path) -> Model:
    """The :class:`Model` of the ``model.json`` at ``path`` (:func:`model_from_document`)."""
    path = Path(path)
    try:
        document = json.loads(path.read_text())
    except FileNotFoundError:
        raise DataFileError(f"{path} does not exist") from None
    except (OSError, ValueError) as exc:
        raise DataFileError(f"{path} is not readable JSON: {exc}") from None
    return model_from_document(document, str(path))
