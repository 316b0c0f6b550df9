"""The calibrated model as a product: ``params.h5`` -> a ready particle :class:`Model`.

``load_model("runs/liver/params.h5")`` (also ``forcecal.load_model``) returns the particle
model a calibration fitted: one particle per vertex of the mesh the file stores, lumped
masses from the scene's density (the ``material`` settings the fit read), the vertices of
the scene's support fixed, one connector per edge with the variant's fitted ``K0, a, b``
and Maxwell arms, and the volume term (elastic or viscoelastic, per tet or nodal) when the
scene had one (``particle.volume``, ``particle.volume_element``). :func:`load_calibrated` returns it with what a user of the model
needs besides: the mesh and test points (:class:`~forcecal.problem.Problem`) and the strain
range the fit required the springs to stay positive on. Every command and benchmark that
runs a calibrated model from ``params.h5`` builds it here (:func:`calibrated_model`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from calibration.results import VARIANTS, CalibrationResult, read_params
from forcecal.errors import DataFileError, ForcecalError
from forcecal.problem import Problem
from particle.model import Model, build_model
from particle.nodal_volume import VOLUME_ELEMENTS


@dataclass(frozen=True, eq=False)
class CalibratedModel:
    """A calibrated particle model and what it was calibrated on.

    Attributes:
        model: the particle model (fixed support, masses, connectors, volume term).
        problem: the mesh, its fixed vertices, the test points with their inward unit
            normals and the tracked vertex of the gravity test.
        variant: the parameter set (``calibrated``, ``global`` or ``baseline``).
        strain_range: (low, high) connector strains [1] on which the fit required every
            spring's K(eps) > 0: the range the springs are valid on.
        density: the scene's mass density [kg/m^3] the masses are lumped from.
        volume: the volume term: None (off), ``"elastic"`` or ``"viscoelastic"``.
        source: the ``params.h5`` it was read from ("" when built from a result in memory).
    """
    model: Model
    problem: Problem
    variant: str
    strain_range: tuple[float, float]
    density: float
    volume: str | None
    source: str = ""


def volume_kind(model: Model) -> str | None:
    """The model's volume term: None (off), ``"elastic"`` or ``"viscoelastic"``."""
    if not model.has_volume:
        return None
    return "viscoelastic" if model.params.has_volume_arms else "elastic"


def _density(result: CalibrationResult, where: str) -> float:
    """The density [kg/m^3] of the ``material`` settings the fit read."""
    value = result.settings.get("material", {}).get("density")
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (
            math.isfinite(value) and value > 0):
        raise DataFileError(f"{where}: settings material.density = {value!r} is not a density "
                            "> 0 kg/m^3 (corrupt or edited file?)")
    return float(value)


def volume_element_of(result: CalibrationResult, where: str) -> str:
    """The volume term's element the fit used (settings ``model``, absent: ``"tet"``)."""
    value = result.settings.get("model", {}).get("particle.volume_element", "tet")
    if value not in VOLUME_ELEMENTS:
        raise DataFileError(f"{where}: settings particle.volume_element = {value!r} is not one "
                            f"of {list(VOLUME_ELEMENTS)} (corrupt or edited file?)")
    return value


def _check_volume(result: CalibrationResult, variant: str, model: Model, where: str) -> None:
    """The fitted variants carry the volume term the scene asked for (``particle.volume``):
    a file whose parameters and settings disagree is damaged or edited."""
    asked = result.settings.get("model", {}).get("particle.volume")
    if asked is None or variant == "baseline":  # the closed form has springs only
        return
    want = {False: None, True: "elastic", "viscoelastic": "viscoelastic"}.get(asked, "?")
    if volume_kind(model) != want:
        raise DataFileError(f"{where}: the {variant} parameters have volume term "
                            f"{volume_kind(model)!r} but the scene's particle.volume = "
                            f"{asked!r} (corrupt or edited file?)")


def calibrated_model(result: CalibrationResult, variant: str = "calibrated",
                     source: str | Path = "") -> CalibratedModel:
    """The particle model of ``variant`` of a calibration ``result`` (read from ``source``).

    Raises :class:`DataFileError` for an unknown variant, a density that is not one, or
    parameters that do not fit the stored mesh or the scene's volume term.
    """
    where = str(source) or "calibration result"
    if variant not in result.connectors:
        raise DataFileError(f"{where}: unknown variant {variant!r}; the variants are "
                            f"{', '.join(v for v in VARIANTS if v in result.connectors)}")
    density = _density(result, where)
    element = volume_element_of(result, where)
    try:
        model = build_model(result.problem, density, result.connectors[variant],
                            volume_element=element)
    except ForcecalError as exc:  # parameters that do not fit the mesh stored next to them
        raise DataFileError(f"{where}: the {variant} parameters do not make a model of the "
                            f"stored mesh: {exc}") from None
    _check_volume(result, variant, model, where)
    return CalibratedModel(model, result.problem, variant, result.strain.bounds, density,
                           volume_kind(model), str(source))


def load_calibrated(path: str | Path, variant: str = "calibrated") -> CalibratedModel:
    """:func:`calibrated_model` of the ``params.h5`` at ``path``.

    Raises :class:`DataFileError` for a missing, unreadable or corrupt file (kind, schema,
    shapes and finiteness are checked) and for an unknown ``variant``.
    """
    if variant not in VARIANTS:  # before reading the file: the cheap refusal first
        raise DataFileError(f"unknown variant {variant!r} of {path}; the variants are "
                            f"{', '.join(VARIANTS)}")
    try:
        result = read_params(path)
    except DataFileError:
        raise
    except ForcecalError as exc:  # e.g. parameters no model accepts: the file is damaged
        raise DataFileError(f"{path}: {exc}") from None
    return calibrated_model(result, variant, path)


def load_model(path: str | Path, variant: str = "calibrated") -> Model:
    """The ready particle model of the ``params.h5`` at ``path`` (module docstring).

    ``variant``: ``"calibrated"`` (global + local tuning, or the gradient fit; default),
    ``"global"`` (the uniform global fit) or ``"baseline"`` (the closed-form Van Gelder
    springs). Raises :class:`DataFileError` for a missing or corrupt file or an unknown
    variant.
    """
    return load_calibrated(path, variant).model
