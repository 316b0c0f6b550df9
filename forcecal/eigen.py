"""Natural modes by shift-invert Lanczos, held and unsupported (free-free).

The FE reference (:mod:`reference_fe.body`) and the particle model (:mod:`particle.body`)
compute the modes of their whole-body data the same way (:func:`nearest_modes`). The
stiffness of an unsupported body is singular (its six rigid modes have zero eigenvalue), so
:func:`free_modes` factorises ``K - sigma M`` with ``sigma`` below zero instead of ``K`` and
leaves out the six rigid modes, nearest the shift.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla

from forcecal.errors import ConvergenceError

#: rigid-body modes of an unsupported body
RIGID_MODES = 6
#: the shift [1/s^2]: (2 pi x 1 Hz)^2 below zero, far under any elastic mode of an organ (tens
#: of Hz unsupported) and well clear of the rigid modes' zero
FREE_SHIFT = -(2.0 * np.pi) ** 2
#: a rigid mode's eigenvalue relative to the first elastic one: round-off of the factorised
#: shift (1e-12 or so), far below any elastic mode
RIGID_TOLERANCE = 1e-6


def nearest_modes(stiffness: sp.spmatrix, mass: sp.spmatrix, count: int, sigma: float,
                  what: str) -> tuple[np.ndarray, np.ndarray]:
    """The ``count`` eigenpairs of ``stiffness phi = lambda mass phi`` nearest ``sigma`` [1/s^2]
    by shift-invert Lanczos on a sparse LU of ``stiffness - sigma mass``: (eigenvalues
    (count,) ascending, M-normalised vectors (n, count)); ``what`` names them in an error.

    Raises:
        ConvergenceError: the eigen-solve did not converge.
    """
    K, M = sp.csc_matrix(stiffness), sp.csc_matrix(mass)
    lu = sla.splu(K if sigma == 0.0 else sp.csc_matrix(K - sigma * M))
    inverse = sla.LinearOperator(K.shape, matvec=lu.solve, dtype=np.float64)
    # a fixed start vector: without one ARPACK draws it from a generator whose state persists
    # in the process, so the same solve's round-off would depend on what was solved before it
    # (a resumed calibration's modes not bitwise an uninterrupted one's)
    start = np.random.default_rng(0).uniform(0.5, 1.5, K.shape[0])
    try:
        values, vectors = sla.eigsh(K, k=count, M=M, sigma=sigma, OPinv=inverse, which="LM",
                                    v0=start)
    except (sla.ArpackError, sla.ArpackNoConvergence) as exc:
        raise ConvergenceError(f"{what}: the eigen-solve did not converge ({exc})") from None
    order = np.argsort(values)
    return values[order], vectors[:, order]


def free_modes(stiffness: sp.spmatrix, mass: sp.spmatrix, count: int, what: str
               ) -> tuple[np.ndarray, np.ndarray]:
    """The ``count`` lowest elastic eigenpairs of ``stiffness phi = lambda mass phi`` for an
    unsupported body: (eigenvalues (count,) [1/s^2] ascending, M-normalised vectors (n,
    count)); ``what`` names them in an error.

    Raises:
        ConvergenceError: the solve did not converge, or the six lowest eigenvalues are not
            rigid modes well below the elastic ones (the body is held somewhere, or is a
            mechanism with more zero modes).
    """
    values, vectors = nearest_modes(stiffness, mass, count + RIGID_MODES, FREE_SHIFT, what)
    rigid, elastic = values[:RIGID_MODES], values[RIGID_MODES:]
    if not (elastic[0] > 0 and np.all(np.abs(rigid) < RIGID_TOLERANCE * elastic[0])):
        raise ConvergenceError(f"{what}: the six lowest eigenvalues {np.round(rigid, 6).tolist()}"
                               f" /s^2 are not rigid modes below the first elastic one "
                               f"{elastic[0]:.4g} /s^2 (is the body held, or a mechanism?)")
    return elastic, vectors[:, RIGID_MODES:]
