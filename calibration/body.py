"""Whole-body data in the gradient fit: residual rows, their coordinate Jacobian, the record.

The FE reference's experiment ``body`` (natural modes, static body loads:
:mod:`reference_fe.body`) is fitted jointly with the surface curves when the scene asks for
it (``experiments`` holding ``body``, ``calibration.body_data`` naming the kinds). Each data
item (one load, one mode at one modulus) is a block of residual rows
(:mod:`particle.body`: relative errors, so an item weighs like a calibration point), times
``sqrt(w)`` with the body weight ``w`` (``calibration.body_weight``, by default chosen by
cross-validation on calibration data only: :func:`calibration.gradient_solver.cross_validate`).

:class:`BodyData` evaluates them in the fit's process (one model: two static solves and two
eigen-solves, next to the surface curves the workers evaluate) and turns
:class:`particle.body.Rows` into compressed coordinate rows: the Jacobian ``L D C`` (virtual
fields, sparse parameter forces, the coordinates' sparse chain matrix) is never formed
densely; an item with more rows than kept (a load: three per free particle) is projected on
the leading singular directions of its Jacobian from the Gram matrix ``L (D C)(D C)^T L^T``.

:func:`body_record` is what ``params.h5`` stores (its ``body`` attribute): whether the fit
used the data, the weight, and every variant's whole-body errors or the reason it has none.
A calibration whose model does not carry a fitted body load (no static equilibrium) is a
**failed calibration**: ``status = "failed"`` with the reason, never a crash.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from calibration.gradient_solver import compress, leading_vectors
from calibration.optimize import INFEASIBLE
from forcecal.errors import ConvergenceError
from forcecal.h5io import Reference
from forcecal.h5io import BodyResult
from particle.body import (BODY_KINDS, BodyResponse, BodyTarget, RestOperators, Rows,
                           available_kinds, body_response)
from particle.model import Model, build_model
from particle.params import ConnectorParams

log = logging.getLogger(__name__)

def body_kinds(setting: str) -> tuple[str, ...]:
    """The kinds (some of :data:`particle.body.BODY_KINDS`) of ``calibration.body_data``
    (``"none"`` or kinds joined by ``+``, :data:`forcecal.scene.BODY_DATA_CHOICES`)."""
    kinds = () if setting == "none" else tuple(setting.split("+"))
    assert set(kinds) <= set(BODY_KINDS), setting
    return kinds


@dataclass(frozen=True, eq=False)
class BodyRows:
    """Compressed coordinate rows of the whole-body data at one parameter set.

    Attributes:
        residual: (R,) residuals [1] (unweighted).
        jacobian: (R, size) their derivatives with respect to the fit's coordinates.
        item: (R,) the data item of each row (index into :attr:`BodyData.items`).
        left_out: squared residual the compression left out of the fitted items' rows [1].
        fitted: (R,) whether each row's item is of a kind the fit uses.
        left_out_every: the same of every item's rows, fitted or only predicted [1].
    """
    residual: np.ndarray
    jacobian: np.ndarray
    item: np.ndarray
    left_out: float
    fitted: np.ndarray
    left_out_every: float


class BodyData:
    """The whole-body data of a fit (module docstring): those it fits (``kinds``) and, for the
    cross-validation's report of how well a fit predicts data it did not see, every kind the
    reference holds.

    Args:
        model: the particle model (topology and masses; parameters come with each call).
        body: the FE's whole-body data.
        kinds: the kinds fitted (some of :data:`particle.body.BODY_KINDS`).
        load_steps: load steps of each static load.
    """

    def __init__(self, model: Model, body: BodyResult, kinds: tuple[str, ...],
                 load_steps: int):
        self.model, self.kinds, self.load_steps = model, tuple(kinds), load_steps
        self.target = BodyTarget.of(body, available_kinds(body))
        self.fitted = BodyTarget.of(body, self.kinds)
        self.ops = RestOperators.of(model, unsupported=self.target.free_frequencies.size > 0)

    @classmethod
    def of(cls, reference: Reference, kinds: tuple[str, ...], params: ConnectorParams,
           load_steps: int) -> "BodyData":
        """The data of ``reference``'s experiment ``body``, ``kinds`` of them fitted."""
        model = build_model(reference.problem, reference.material.density, params)
        return cls(model, reference.body, kinds, load_steps)

    def with_kinds(self, kinds: tuple[str, ...]) -> "BodyData":
        """The same data with ``kinds`` fitted (model and operators shared)."""
        out = object.__new__(BodyData)
        out.__dict__.update(self.__dict__)
        out.kinds = tuple(kinds)
        out.fitted = self.target.subset(out.kinds)
        return out

    def carried(self, params: ConnectorParams) -> dict[str, str | None]:
        """For each fitted kind, None if the model at ``params`` has a response to every item
        of it (an equilibrium under each load, its modes), else why not."""
        out = {}
        for kind in self.kinds:
            try:
                self.with_kinds((kind,)).response(params, fitted=True, jacobian=False)
                out[kind] = None
            except INFEASIBLE as exc:
                out[kind] = f"{type(exc).__name__}: {exc}"
        return out

    @property
    def items(self) -> list[str]:
        """Every data item (fitted or not), in row order."""
        return self.target.items

    @property
    def item_kinds(self) -> list[str]:
        """The kind of each of :attr:`items`."""
        return self.target.item_kinds

    def response(self, params: ConnectorParams, *, fitted: bool = False,
                 jacobian: bool = True) -> BodyResponse:
        """The model's whole-body response at ``params`` against every item, or the fitted
        ones only, with its Jacobian or (``jacobian`` False) its residuals alone (raises what
        :func:`particle.body.body_response` raises)."""
        return body_response(self.model.with_params(params),
                             self.fitted if fitted else self.target, self.load_steps, self.ops,
                             jacobian=jacobian)

    def residuals(self, params: ConnectorParams) -> np.ndarray:
        """(R,) the fitted items' unweighted residuals at ``params`` (rows uncompressed)."""
        return self.response(params, fitted=True, jacobian=False).residual

    def responses(self, params: ConnectorParams, *, every: bool = True,
                  jacobian: bool = True) -> tuple[dict[str, BodyResponse], dict[str, str]]:
        """Kind by kind, the model's response at ``params`` to every item of each kind that
        has one (``every`` False: of the fitted kinds only), and why the others have none
        ({kind: reason}); with the Jacobians, or (``jacobian`` False) the residuals alone."""
        model = self.model.with_params(params)
        out, failures = {}, {}
        for kind in dict.fromkeys(self.item_kinds):
            if not every and kind not in self.kinds:
                continue
            try:
                out[kind] = body_response(model, self.target.subset((kind,)), self.load_steps,
                                          self.ops, jacobian=jacobian)
            except INFEASIBLE as exc:
                failures[kind] = f"{type(exc).__name__}: {exc}"
        return out, failures

    def rows(self, params: ConnectorParams, chain: sp.csr_matrix, keep: int, *,
             every: bool = True) -> BodyRows:
        """The compressed coordinate rows at ``params`` of every item of the fitted kinds and
        (``every``: what the cross-validation predicts) of the other kinds the model has a
        response to (those it has none to give no rows: the cross-validation cannot predict
        them); ``chain`` (P, size) the fit's chain matrix from the parameter layout to its
        coordinates (:meth:`calibration.gradient.Coordinates.chain_matrix`).

        Raises:
            ConvergenceError: no response to a fitted kind.
        """
        responses, failures = self.responses(params, every=every)
        for kind in self.kinds:
            if kind in failures:
                raise ConvergenceError(f"whole-body data {kind}: {failures[kind]}")
        kinds = self.item_kinds
        residual, jacobian, item, left, left_every = [], [], [], 0.0, 0.0
        for kind, response in responses.items():
            first = kinds.index(kind)
            for k, part in enumerate(response.parts):
                r, J, out = compress_rows(part, chain, keep)
                residual.append(r)
                jacobian.append(J)
                item.append(np.full(len(r), first + k))
                left += out if kind in self.kinds else 0.0
                left_every += out
        item = np.concatenate(item)
        return BodyRows(np.concatenate(residual), np.vstack(jacobian), item, left,
                        np.isin(np.array(kinds)[item], self.kinds), left_every)


def compress_rows(part: Rows, chain: sp.csr_matrix, keep: int
                  ) -> tuple[np.ndarray, np.ndarray, float]:
    """(residual (k,), coordinate Jacobian (k, size), squared residual left out) of one
    item: its rows projected on the ``keep`` leading left singular vectors of its Jacobian
    ``L (D C) + X C`` when it has more rows (as :func:`calibration.gradient_solver.compress`
    does for a point's curve samples), from the Gram matrix so that no (rows, size) block is
    formed (an item with an explicit part ``X`` has few rows: it is formed)."""
    forces = sp.csr_matrix(part.forces @ chain)  # (n, size)
    fields, r = part.fields, part.residual
    if part.explicit is not None:
        jacobian = (np.asarray((forces.T @ fields.T).T)
                    + np.asarray((sp.csr_matrix(part.explicit) @ chain).todense()))
        if len(r) <= keep:
            return r, jacobian, 0.0
        return compress(r, jacobian, len(r), keep)
    left = 0.0
    if len(r) > keep:
        gram = fields @ np.asarray((forces @ forces.T).todense()) @ fields.T
        U = leading_vectors(gram, keep)
        fields, r_kept = U.T @ fields, U.T @ r
        left = float(r @ r - r_kept @ r_kept)
        r = r_kept
    return r, np.asarray((forces.T @ fields.T).T), left


def variant_summary(data: BodyData, params: ConnectorParams) -> dict:
    """One parameter set's whole-body errors (:meth:`particle.body.BodyResponse.summary`) on
    every item it has a response to, ``item_errors`` in :attr:`BodyData.items` order (NaN
    where it has none), and ``failures`` {kind: reason} with ``failure`` (the first reason)
    for the kinds it has none to."""
    responses, failures = data.responses(params, jacobian=False)
    errors = np.full(len(data.items), np.nan)
    kinds = data.item_kinds
    out: dict = {}
    load_errors: list[float] = []
    for kind, response in responses.items():
        first = kinds.index(kind)
        summary = response.summary()
        errors[first:first + len(summary["item_errors"])] = summary["item_errors"]
        load_errors += summary["load_errors"]
        out.update({k: v for k, v in summary.items()
                    if k not in ("items", "item_errors", "load_errors")})
    out.update({"item_errors": [None if np.isnan(e) else float(e) for e in errors],
                "load_errors": load_errors})
    if failures:
        out["failures"] = failures
        out["failure"] = next(iter(failures.values()))
    return out


def body_record(data: BodyData, weight: float | None, connectors: dict[str, ConnectorParams],
                failure: str | None = None, cv: dict | None = None) -> dict:
    """The ``body`` record of ``params.h5``.

    ``status``: ``"fitted"`` (``data.kinds`` were fitted with ``weight`` > 0 and the calibrated
    model has a response to each: an equilibrium under every fitted load, its modes),
    ``"failed"`` (it has none for a fitted item: a failed calibration; ``failure`` says
    why) or ``"not fitted"`` (none asked for, a weight of 0, or ``failure`` says why they
    could not be used: ``weight`` None). ``variants``: each variant's errors against every
    item (fitted or not), or ``{"failure": reason}``. ``cv``: the cross-validation's
    candidate scores (:func:`candidate_scores`), when computed.
    """
    variants = {name: variant_summary(data, params) for name, params in connectors.items()}
    status = "fitted" if data.kinds and weight else "not fitted"
    if status == "fitted":
        try:
            data.response(connectors["calibrated"], fitted=True, jacobian=False)
        except INFEASIBLE as exc:
            status = "failed"
            failure = ("the calibrated model does not carry the whole-body data it was fitted "
                       f"to: {type(exc).__name__}: {exc}")
    return {"status": status, "kinds": list(data.kinds), "weight": weight, "failure": failure,
            "items": data.items, "variants": variants, **({"cv": cv} if cv else {})}
