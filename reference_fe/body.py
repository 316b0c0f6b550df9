"""Whole-body data of the FE reference (experiment ``body``): natural modes and static body loads.

The surface curves (indentation, relaxation) pin the particle model's stiffness under the
indenter; nothing in them constrains how the body as a whole hangs or swings. This
experiment gives the calibration two kinds of whole-body data that the gravity test does
not use (its gravity direction and its release stay held out):

* **natural modes** about the undeformed rest state with the scene's support, at the
  instantaneous moduli (the material's ``C10, C01``: what a motion of a few hertz feels,
  both Prony times being long against its period) and at the long-term ones (``g_inf``
  times them): the ``body.modes`` lowest frequencies [Hz] and their mode shapes at the
  particle vertices, from the linearised stiffness ``K`` (the Jacobian of the FE residual
  at ``u = 0``) and the consistent mass ``M`` (the Jacobian's inertia term per unit
  ``c_m``), ``K phi = omega^2 M phi`` with the clamp's dofs removed, by shift-invert
  Lanczos (:func:`scipy.sparse.linalg.eigsh` on a sparse LU of ``K``; for Taylor-Hood ``M``
  is zero on the pressure dofs, which shift-invert tolerates: their eigenvalues are
  infinite and never among the lowest). Shapes are mass-normalised with the FE's mass
  (``phi^T M phi = 1``), each signed so its largest vertex component is positive;
* **static body loads**: the organ's weight (``|gravity.acceleration|``) along the two
  directions perpendicular to the test's gravity (:func:`load_directions`), each a
  nonlinear, long-term, load-stepped static solve exactly like the gravity sag's
  (:func:`reference_fe.experiments.gravity_static`).

Both run on the model of the gravity experiments (the particle mesh refined ``fe.refine``
times, read back at the particle vertices). Cost: two eigen-solves and two static solves,
measured on the liver punch scene (Taylor-Hood on the particle mesh, 5,328 dofs) at ~1.5 s
per eigen-solve and about the gravity sag's time per load.
"""

from __future__ import annotations

import logging

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla
from dolfinx.fem.petsc import assemble_matrix

from forcecal.errors import ConvergenceError
from forcecal.h5io import BodyResult
from reference_fe.experiments import gravity_static
from reference_fe.model import FEModel, _set_material, initial_state

log = logging.getLogger(__name__)

#: the moduli the modes are computed at, in the order of :class:`forcecal.h5io.BodyResult`
MODULI = ("instantaneous", "long_term")


def load_directions(acceleration: np.ndarray) -> np.ndarray:
    """(2, 3) unit vectors perpendicular to ``acceleration`` and to each other: the coordinate
    axis least aligned with gravity with gravity projected out, then gravity's direction
    crossed with it (for gravity along a coordinate axis: the other two axes, positive)."""
    g = np.asarray(acceleration, dtype=np.float64)
    g = g / np.linalg.norm(g)
    first = np.eye(3)[int(np.argmin(np.abs(g)))]
    first = first - (first @ g) * g
    first /= np.linalg.norm(first)
    second = np.cross(g, first)
    if np.count_nonzero(np.abs(second) > 1e-12) == 1:  # an axis: point it the positive way
        second = np.abs(second)
    return np.stack([first, second / np.linalg.norm(second)])


def static_loads(model: FEModel, fixed: np.ndarray, acceleration: np.ndarray,
                 load_steps: int) -> tuple[np.ndarray, np.ndarray]:
    """The organ's weight along each of :func:`load_directions`: ((2, 3) directions, (2, N, 3)
    static displacements of every FE vertex [m]), long-term material, ``load_steps``
    increments each (as the gravity sag)."""
    directions = load_directions(acceleration)
    magnitude = float(np.linalg.norm(acceleration))
    displacement = np.stack([gravity_static(model, fixed, magnitude * d, load_steps)
                             for d in directions])
    return directions, displacement


def _assembled(model: FEModel, inertia: float) -> sp.csr_matrix:
    """The residual's Jacobian at ``u = 0`` with the inertia coefficient ``c_m = inertia``."""
    model._c_m.value = inertia
    model.w.x.array[:] = 0.0
    matrix = assemble_matrix(model._problem.a)
    matrix.assemble()
    indptr, indices, data = matrix.getValuesCSR()
    model._c_m.value = 0.0
    return sp.csr_matrix((data, indices, indptr), shape=matrix.getSize())


def _set_moduli(model: FEModel, modulus: str) -> None:
    """The model's material constants for a rest-state tangent at ``modulus``: the long-term
    hyperelastic material, or the instantaneous one (``gamma = 1``, no Prony history: the
    response to a step before any relaxation)."""
    if modulus == "long_term":
        _set_material(model, initial_state(model), None)
        return
    m = model.material
    model._C10.value, model._C01.value, model._gamma.value = m.C10, m.C01, 1.0
    model._hist.x.array[:] = 0.0


def stiffness_and_mass(model: FEModel, modulus: str) -> tuple[sp.csr_matrix, sp.csr_matrix]:
    """(K, M) of the whole solution vector at the rest state: the linearised stiffness at the
    ``modulus`` (:data:`MODULI`) [N/m] and the consistent mass [kg] (zero on pressure dofs)."""
    if modulus not in MODULI:
        raise ValueError(f"modulus {modulus!r}: must be one of {MODULI}")
    _set_moduli(model, modulus)
    stiffness = _assembled(model, 0.0)
    return stiffness, _assembled(model, 1.0) - stiffness


def natural_modes(model: FEModel, fixed: np.ndarray, count: int, modulus: str
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The ``count`` lowest natural modes at ``modulus``, support = the clamp of ``fixed``:
    ((count,) frequencies [Hz] ascending, (count, N, 3) mass-normalised shapes at the FE
    vertices [1/sqrt(kg)]).

    Raises:
        ConvergenceError: the eigen-solve did not converge, or gave a non-positive
            eigenvalue (a support that does not hold the body).
    """
    stiffness, mass = stiffness_and_mass(model, modulus)
    held = model.clamp_dofs(fixed).ravel()
    free = np.setdiff1d(np.arange(model.n_dofs), held)
    K = stiffness[free][:, free].tocsc()
    M = mass[free][:, free].tocsc()
    lu = sla.splu(K)
    inverse = sla.LinearOperator(K.shape, matvec=lu.solve, dtype=np.float64)
    try:
        values, vectors = sla.eigsh(K, k=count, M=M, sigma=0.0, OPinv=inverse, which="LM")
    except (sla.ArpackError, sla.ArpackNoConvergence) as exc:
        raise ConvergenceError(f"body modes at the {modulus} moduli: the eigen-solve did not "
                               f"converge ({exc})") from None
    order = np.argsort(values)
    values, vectors = values[order], vectors[:, order]
    if not np.all(values > 0):
        raise ConvergenceError(f"body modes at the {modulus} moduli: eigenvalue "
                               f"{values.min():.3g} <= 0; the support does not hold the body")
    full = np.zeros((model.n_dofs, count))
    full[free] = vectors
    shapes = np.moveaxis(full[model.vertex_dofs], 2, 0)  # (count, N, 3)
    for k in range(count):  # a deterministic sign: the largest vertex component positive
        flat = shapes[k].ravel()
        shapes[k] *= np.sign(flat[np.argmax(np.abs(flat))])
    frequencies = np.sqrt(values) / (2.0 * np.pi)
    log.debug("body modes at the %s moduli: %s Hz", modulus, np.round(frequencies, 3).tolist())
    return frequencies, shapes


def body_data(model: FEModel, fixed: np.ndarray, acceleration: np.ndarray, modes: int,
              load_steps: int) -> dict[str, np.ndarray]:
    """The arrays of the ``body`` work item at the FE vertices: ``frequencies`` (2, M) [Hz]
    and ``shapes`` (2, M, N, 3) of :data:`MODULI`, ``load_directions`` (2, 3) and
    ``load_displacement`` (2, N, 3) [m]."""
    frequencies, shapes = zip(*(natural_modes(model, fixed, modes, m) for m in MODULI))
    directions, displacement = static_loads(model, fixed, acceleration, load_steps)
    return {"frequencies": np.stack(frequencies), "shapes": np.stack(shapes),
            "load_directions": directions, "load_displacement": displacement}


def at_vertices(arrays: dict[str, np.ndarray], vertices: np.ndarray) -> dict[str, np.ndarray]:
    """The arrays of :func:`body_data` read at the FE vertices ``vertices`` (the particle
    vertices on a refined FE mesh)."""
    return {**arrays, "shapes": arrays["shapes"][:, :, vertices],
            "load_displacement": arrays["load_displacement"][:, vertices]}


def result_of(arrays: dict[str, np.ndarray], acceleration: float) -> BodyResult:
    """The :class:`~forcecal.h5io.BodyResult` of a work item's arrays (:func:`body_data` at the
    particle vertices); ``acceleration`` the loads' magnitude [m/s^2]."""
    return BodyResult(frequencies=arrays["frequencies"], shapes=arrays["shapes"],
                      load_directions=arrays["load_directions"], load_acceleration=acceleration,
                      load_displacement=arrays["load_displacement"])


def arrays_of(result: BodyResult) -> dict[str, np.ndarray]:
    """A stored :class:`~forcecal.h5io.BodyResult` as the work item's arrays (:func:`result_of`'s
    inverse)."""
    return {"frequencies": result.frequencies, "shapes": result.shapes,
            "load_directions": result.load_directions,
            "load_displacement": result.load_displacement}
