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
* **natural modes of the unsupported body** (free-free, :func:`unsupported_modes`) at the
  same two moduli, its six rigid modes left out: a clamp's modes are felt mostly near the
  clamp, these weigh the whole body's stiffness without a support's bias;
* **static body loads**: the organ's weight (``|gravity.acceleration|``) along the two
  directions perpendicular to the test's gravity
  (:func:`forcecal.problem.body_load_directions`), each a
  nonlinear, long-term, load-stepped static solve exactly like the gravity sag's
  (:func:`reference_fe.experiments.gravity_static`). A support that holds the body under
  the test's gravity may not hold it sideways (a narrow seat lets it swing over): then the
  loads and their modes are left out, with the reason (``load_failure``), and the modes
  kept, so the calibration fits what the FE could compute;

* **modes about each loaded state**: the ``body.modes`` lowest modes of small motions
  about each static load's equilibrium, at the instantaneous incremental moduli (the
  material relaxed under the load, a quick motion about it: ``gamma = 1`` with the Prony
  history ``H = -(1 - g_inf) S_iso0`` at the equilibrium, so the stress is the long-term
  one and its increments the instantaneous ones; the stress enters the tangent's geometric
  part): how the body's stiffness changes under a load of its own weight's size, which the
  rest-state modes do not tell (a release swings about a loaded state).

Both run on the model of the gravity experiments (the particle mesh refined ``fe.refine``
times, read back at the particle vertices). Cost: four eigen-solves and two static solves,
measured on the liver punch scene (Taylor-Hood on the particle mesh, 5,328 dofs) at ~1.5 s
per eigen-solve and about the gravity sag's time per load.
"""

from __future__ import annotations

import logging

import numpy as np
import scipy.sparse as sp
import ufl
from dolfinx import fem
from dolfinx.fem.petsc import assemble_matrix

from forcecal.eigen import free_modes, nearest_modes
from forcecal.errors import ConvergenceError, StabilityError
from forcecal.h5io import BodyResult
from forcecal.problem import body_load_directions
from reference_fe.experiments import gravity_static
from reference_fe.model import (JIT_PARAMS, FEModel, _set_material, initial_state,
                                quadrature_measure, second_piola_kirchhoff)

log = logging.getLogger(__name__)

#: the moduli the modes are computed at, in the order of :class:`forcecal.h5io.BodyResult`
MODULI = ("instantaneous", "long_term")


def static_loads(model: FEModel, fixed: np.ndarray, acceleration: np.ndarray,
                 load_steps: int, modes: int = 0
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The organ's weight along each of :func:`forcecal.problem.body_load_directions`: ((2, 3)
    directions, (2, N, 3) static displacements of every FE vertex [m]), long-term material,
    ``load_steps`` increments each (as the gravity sag); and the ``modes`` lowest modes about
    each equilibrium (:func:`loaded_modes`: (2, modes) frequencies [Hz], (2, modes, N, 3)
    shapes; empty for ``modes`` 0)."""
    directions = body_load_directions(acceleration)
    magnitude = float(np.linalg.norm(acceleration))
    displacement, frequencies, shapes = [], [], []
    for d in directions:
        u, state = gravity_static(model, fixed, magnitude * d, load_steps, with_state=True,
                                  what=f"the weight along {np.round(d, 3).tolist()} (static)")
        displacement.append(u)
        if modes:
            f, phi = loaded_modes(model, fixed, state.u, modes)
            frequencies.append(f)
            shapes.append(phi)
    n = model.mesh.n_vertices
    return (directions, np.stack(displacement),
            np.stack(frequencies) if modes else np.zeros((len(directions), 0)),
            np.stack(shapes) if modes else np.zeros((len(directions), 0, n, 3)))


def loaded_modes(model: FEModel, fixed: np.ndarray, u: np.ndarray, count: int, *,
                 initial_stress: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """The ``count`` lowest modes of small motions about the long-term static equilibrium
    ``u`` (a solution vector), at the instantaneous incremental moduli (module docstring);
    without ``initial_stress``, of the tangent less its initial-stress part
    (:func:`initial_stress_stiffness`: the material stiffness about the loaded shape alone)."""
    m = model.material
    model._C10.value, model._C01.value, model._gamma.value = m.C10, m.C01, 1.0
    model._hist.x.array[:] = 0.0
    model.w.x.array[:] = u
    model.set_history(-(1.0 - m.long_term_factor) * model.isochoric_stress_at_quadrature_points())
    model._gravity.value[:] = 0.0  # a constant load: no part of the tangent
    stiffness = _assembled(model, 0.0, u)
    mass = _assembled(model, 1.0, u) - stiffness  # leaves the unknown at u
    if not initial_stress:
        stiffness = stiffness - initial_stress_stiffness(model)
    return _lowest_modes(model, fixed, stiffness, mass, count,
                         "about a loaded state" + ("" if initial_stress
                                                   else " without its initial stress"))


def initial_stress_stiffness(model: FEModel) -> sp.csr_matrix:
    """(n, n) the initial-stress part of the residual's Jacobian [N/m], whole solution vector,
    at the model's current unknown and material constants: ``int grad(du) S : grad(v)``
    with ``S`` the residual's second Piola-Kirchhoff stress (the stiffness a stress adds to
    small motions about it, as a taut string's). The rest of the Jacobian is the material
    part ``int F dS[du] : grad(v)`` (and the pressure's rows for the u-p elements)."""
    _, _, S, _ = second_piola_kirchhoff(model, model.material.kappa)
    trial, test = ufl.TrialFunction(model.space), ufl.TestFunction(model.space)
    if model._is_mixed:
        trial, test = ufl.split(trial)[0], ufl.split(test)[0]
    form = fem.form(ufl.inner(ufl.grad(trial) * S, ufl.grad(test)) * quadrature_measure(model),
                    jit_params=JIT_PARAMS)
    matrix = assemble_matrix(form)
    matrix.assemble()
    indptr, indices, data = matrix.getValuesCSR()
    return sp.csr_matrix((data, indices, indptr), shape=matrix.getSize())


def _assembled(model: FEModel, inertia: float, u: np.ndarray | None = None) -> sp.csr_matrix:
    """The residual's Jacobian at ``u`` (None: 0) with the inertia coefficient ``c_m =
    inertia``."""
    model._c_m.value = inertia
    model.w.x.array[:] = 0.0 if u is None else u
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


def stiffness_and_mass(model: FEModel, modulus: str, u: np.ndarray | None = None
                       ) -> tuple[sp.csr_matrix, sp.csr_matrix]:
    """(K, M) of the whole solution vector at the rest state (or at the solution vector ``u``
    with the rest state's material: the tangent a quasi-static Newton step sees there): the
    linearised stiffness at the ``modulus`` (:data:`MODULI`) [N/m] and the consistent mass
    [kg] (zero on pressure dofs)."""
    if modulus not in MODULI:
        raise ValueError(f"modulus {modulus!r}: must be one of {MODULI}")
    _set_moduli(model, modulus)
    stiffness = _assembled(model, 0.0, u)
    return stiffness, _assembled(model, 1.0, u) - stiffness


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
    return _lowest_modes(model, fixed, stiffness, mass, count, f"at the {modulus} moduli")


def unsupported_modes(model: FEModel, count: int, modulus: str
                      ) -> tuple[np.ndarray, np.ndarray]:
    """The ``count`` lowest natural modes at ``modulus`` of the unsupported body (free-free,
    its six rigid modes left out: :func:`forcecal.eigen.free_modes`): ((count,) frequencies
    [Hz] ascending, (count, N, 3) mass-normalised shapes at the FE vertices [1/sqrt(kg)],
    signed as :func:`natural_modes`'). They weigh the body's stiffness without the support's
    bias: a clamp's modes are felt mostly near it.

    Raises:
        ConvergenceError: the eigen-solve did not converge or found no six rigid modes.
    """
    stiffness, mass = stiffness_and_mass(model, modulus)
    values, vectors = free_modes(stiffness, mass, count,
                                 f"body modes of the unsupported body at the {modulus} moduli")
    return _frequencies_and_shapes(model, values, vectors, f"unsupported at the {modulus} moduli")


def eigenvalues_nearest_zero(model: FEModel, fixed: np.ndarray, stiffness: sp.csr_matrix,
                             mass: sp.csr_matrix, count: int, what: str
                             ) -> tuple[np.ndarray, np.ndarray]:
    """The ``count`` eigenvalues ``lambda`` of ``stiffness phi = lambda mass phi`` nearest zero
    (whole solution vector assembled; the clamp of ``fixed`` removed), ascending, signed (a
    negative one: the equilibrium is unstable), [1/s^2] for a stiffness [N/m] and a mass [kg];
    and their (n_dofs, count) eigenvectors (zero on the clamped dofs). ``what`` names them in
    an error.

    Raises:
        ConvergenceError: the eigen-solve did not converge.
    """
    held = model.clamp_dofs(fixed).ravel()
    free = np.setdiff1d(np.arange(model.n_dofs), held)
    values, vectors = nearest_modes(stiffness[free][:, free], mass[free][:, free], count, 0.0,
                                    f"body modes {what}")
    full = np.zeros((model.n_dofs, count))
    full[free] = vectors
    return values, full


def _lowest_modes(model: FEModel, fixed: np.ndarray, stiffness: sp.csr_matrix,
                  mass: sp.csr_matrix, count: int, what: str) -> tuple[np.ndarray, np.ndarray]:
    """:func:`natural_modes` of the assembled ``stiffness`` and ``mass`` (whole solution
    vector); ``what`` names them in an error."""
    values, full = eigenvalues_nearest_zero(model, fixed, stiffness, mass, count, what)
    if not np.all(values > 0):
        raise ConvergenceError(f"body modes {what}: eigenvalue {values.min():.3g} <= 0; the "
                               "support does not hold the body")
    return _frequencies_and_shapes(model, values, full, what)


def _frequencies_and_shapes(model: FEModel, values: np.ndarray, full: np.ndarray, what: str
                            ) -> tuple[np.ndarray, np.ndarray]:
    """((count,) frequencies [Hz], (count, N, 3) shapes at the FE vertices, each signed so its
    largest vertex component is positive) of eigenvalues ``values`` [1/s^2] and eigenvectors
    ``full`` (n_dofs, count)."""
    count = len(values)
    shapes = np.moveaxis(full[model.vertex_dofs], 2, 0)  # (count, N, 3)
    for k in range(count):  # a deterministic sign: the largest vertex component positive
        flat = shapes[k].ravel()
        shapes[k] *= np.sign(flat[np.argmax(np.abs(flat))])
    frequencies = np.sqrt(values) / (2.0 * np.pi)
    log.debug("body modes %s: %s Hz", what, np.round(frequencies, 3).tolist())
    return frequencies, shapes


def body_data(model: FEModel, fixed: np.ndarray, acceleration: np.ndarray, modes: int,
              load_steps: int) -> dict[str, np.ndarray]:
    """The arrays of the ``body`` work item at the FE vertices: ``frequencies`` (2, M) [Hz]
    and ``shapes`` (2, M, N, 3) of :data:`MODULI`, ``load_directions`` (2, 3),
    ``load_displacement`` (2, N, 3) [m], ``loaded_frequencies`` (2, M) [Hz] and
    ``loaded_shapes`` (2, M, N, 3) about each load's equilibrium, ``free_frequencies`` (2, M)
    and ``free_shapes`` (2, M, N, 3) of the unsupported body."""
    frequencies, shapes = zip(*(natural_modes(model, fixed, modes, m) for m in MODULI))
    free_f, free_phi = zip(*(unsupported_modes(model, modes, m) for m in MODULI))
    failure = {}
    try:
        directions, displacement, loaded_f, loaded_phi = static_loads(model, fixed, acceleration,
                                                                      load_steps, modes)
    except (ConvergenceError, StabilityError) as exc:
        # the support holds the body under the scene's gravity (its own test) but not under
        # its weight sideways: the loads and their modes are left out, the modes kept
        log.warning("body: the static body loads are left out: %s", exc)
        n = model.mesh.n_vertices
        directions, displacement = np.zeros((0, 3)), np.zeros((0, n, 3))
        loaded_f, loaded_phi = np.zeros((0, modes)), np.zeros((0, modes, n, 3))
        failure = {"load_failure": np.array(str(exc))}
    return {"frequencies": np.stack(frequencies), "shapes": np.stack(shapes),
            "load_directions": directions, "load_displacement": displacement,
            "loaded_frequencies": loaded_f, "loaded_shapes": loaded_phi,
            "free_frequencies": np.stack(free_f), "free_shapes": np.stack(free_phi), **failure}


def at_vertices(arrays: dict[str, np.ndarray], vertices: np.ndarray) -> dict[str, np.ndarray]:
    """The arrays of :func:`body_data` read at the FE vertices ``vertices`` (the particle
    vertices on a refined FE mesh)."""
    return {**arrays, "shapes": arrays["shapes"][:, :, vertices],
            "load_displacement": arrays["load_displacement"][:, vertices],
            "loaded_shapes": arrays["loaded_shapes"][:, :, vertices],
            "free_shapes": arrays["free_shapes"][:, :, vertices]}


def result_of(arrays: dict[str, np.ndarray], acceleration: float) -> BodyResult:
    """The :class:`~forcecal.h5io.BodyResult` of a work item's arrays (:func:`body_data` at the
    particle vertices); ``acceleration`` the loads' magnitude [m/s^2]."""
    return BodyResult(frequencies=arrays["frequencies"], shapes=arrays["shapes"],
                      load_directions=arrays["load_directions"], load_acceleration=acceleration,
                      load_displacement=arrays["load_displacement"],
                      loaded_frequencies=arrays["loaded_frequencies"],
                      loaded_shapes=arrays["loaded_shapes"],
                      free_frequencies=arrays.get("free_frequencies"),
                      free_shapes=arrays.get("free_shapes"),
                      load_failure=(str(arrays["load_failure"]) if "load_failure" in arrays
                                    else None))


def arrays_of(result: BodyResult) -> dict[str, np.ndarray]:
    """A stored :class:`~forcecal.h5io.BodyResult` as the work item's arrays (:func:`result_of`'s
    inverse)."""
    return {"frequencies": result.frequencies, "shapes": result.shapes,
            "load_directions": result.load_directions,
            "load_displacement": result.load_displacement,
            "loaded_frequencies": result.loaded_frequencies,
            "loaded_shapes": result.loaded_shapes,
            **({} if result.free_frequencies is None else
               {"free_frequencies": result.free_frequencies, "free_shapes": result.free_shapes}),
            **({} if result.load_failure is None else
               {"load_failure": np.array(result.load_failure)})}
