"""The discretised organ (:class:`FEModel`), its mutable :class:`FEState` and one Newton step.

:class:`FEModel` turns a :class:`~forcecal.mesh.TetMesh` into dolfinx objects
on ``MPI.COMM_SELF``, once per process: function space, compiled residual and
Jacobian forms, Newton solver (GMRES on a kept MUMPS LDL^T factorisation, chord steps). Every
experiment then reuses them; only the
Dirichlet conditions, the constants (load, material scaling, time step) and
the coefficient arrays change between steps, so forms are compiled once.

One residual form serves every experiment (total Lagrangian, test function v)::

    R(w; v) = int F S(u) : grad v  -  int rho g . v  +  int rho c_m (u - u_pred) . v
              [ + int (J - 1 - p/kappa) q   for the u-p elements TH and ANP ]
    S(u)    = S_vol(u) + gamma S_iso0(u; C10, C01) + H

(see :mod:`reference_fe.material` for ``gamma`` and ``H``). Quasi-static steps
use ``c_m = 0``; dynamic steps (Newmark average acceleration, see
:func:`solve_step`) ``c_m = 4/dt^2``. The residual vector assembled without
Dirichlet conditions is the nodal force the body exerts: at a prescribed
vertex it is the force the indenter applies to it.
"""

from __future__ import annotations

import logging
import time
import weakref
from dataclasses import dataclass, field

import basix
import dolfinx
import numpy as np
import ufl
from dolfinx import fem
from dolfinx import mesh as dmesh
from dolfinx.fem.assemble import pack_coefficients
from dolfinx.fem.petsc import NonlinearProblem, assemble_vector, create_matrix, set_bc
from dolfinx.nls.petsc import NewtonSolver
from mpi4py import MPI
from petsc4py import PETSc

from forcecal.errors import ParameterError
from forcecal.mesh import TetMesh
from forcecal.scene import FESection, MaterialSection
from reference_fe.material import (check_material, isochoric_stress, long_term, pressure_stress,
                                   prony_step)

log = logging.getLogger(__name__)

ELEMENTS = ("P1", "P2", "TH", "ANP")
#: the u-p elements (a pressure field next to the displacement)
MIXED_ELEMENTS = ("TH", "ANP")
#: the elements whose displacement dofs are the mesh vertices' alone (no mid-edge nodes)
VERTEX_ELEMENTS = ("P1", "ANP")


class StepFailed(Exception):
    """A Newton solve did not converge (internal: the caller cuts the step)."""


@dataclass(frozen=True)
class Constraint:
    """Prescribed value of one displacement component on a set of degrees of freedom.

    Attributes:
        component: 0, 1 or 2 (x, y, z).
        dofs: (K,) int32, indices into the solution vector (from :attr:`FEModel.vertex_dofs`
            or :meth:`FEModel.clamp_dofs`) of that component.
        value: prescribed displacement [m].
    """
    component: int
    dofs: np.ndarray
    value: float

    def __post_init__(self) -> None:
        # dolfinx wants a contiguous int32 array (a column slice of vertex_dofs is not)
        object.__setattr__(self, "dofs", np.ascontiguousarray(self.dofs, dtype=np.int32))


@dataclass(frozen=True)
class Load:
    """What a step prescribes: Dirichlet constraints and the gravitational acceleration.

    Attributes:
        constraints: every prescribed displacement component.
        gravity: (3,) float64, body-force acceleration [m/s^2] (zero for indentation).
    """
    constraints: tuple[Constraint, ...]
    gravity: np.ndarray = field(default_factory=lambda: np.zeros(3))


@dataclass
class FEState:
    """State of one experiment after a converged step. :func:`solve_step` returns a new one
    and never modifies its input, so a failed step simply retries from the old state.

    Attributes:
        u: (n_dofs,) float64, solution vector: displacement [m] (and pressure [Pa] for TH).
        velocity: (n_dofs,) float64, d(u)/dt [m/s] (dynamic runs only, zeros otherwise).
        history: (m, n_cells, n_qp, 9) float64, Prony internal variables h_i [Pa]
            at the quadrature points (row-major 3x3 tensors).
        s_iso: (n_cells, n_qp, 9) float64, instantaneous isochoric 2nd PK stress S_iso0 [Pa].
        force: (n_dofs,) float64, residual R(u) assembled with c_m = 0 and without
            Dirichlet rows [N]: the force needed to hold each dof (at a prescribed dof, the
            reaction; in a dynamic run, -(mass x acceleration)). None before the first step.
        progress: value of the experiment's control variable at this state (depth [m],
            time [s] or load factor [1]).
    """
    u: np.ndarray
    velocity: np.ndarray
    history: np.ndarray
    s_iso: np.ndarray
    force: np.ndarray | None
    progress: float


# Linear solves of Newton (see configure_linear_solver): GMRES to this relative residual, at
# most KRYLOV_MAX_IT iterations; the factorisation is refreshed after a solve that needed
# more than KRYLOV_REFRESH_IT of them
KRYLOV_RTOL = 1e-8
KRYLOV_MAX_IT = 100
KRYLOV_REFRESH_IT = 20
# A Newton iteration is a chord step (one back-solve with the kept factorisation, no tangent)
# while the residual fell at least this much over the iteration before, for at most
# CHORD_MAX_ITERATIONS iterations of a solve (see _ResidualProblem)
CHORD_CONTRACTION = 0.5
CHORD_MAX_ITERATIONS = 12
# A chord step is Anderson-mixed with up to this many chord steps before it in the same solve
# (0: plain chord steps; see _ResidualProblem.update)
ANDERSON_DEPTH = 4
# A Newton solve whose residual norm [N] grows past this factor times the largest of its first
# two residuals and the last converged state's force norm is given up at once (StepFailed: the
# step is cut) instead of iterating on to newton_max_it or to a NaN. The first Newton update
# is measured against itself: from rest under a small load, the linearised step's residual
# (its nonlinearity: a slender part rotating, a nearly incompressible element changing
# volume) can exceed the load's a thousand times, and the next Newton update removes it (a
# 1446-vertex figure at 0.4 % of gravity: 2e-4 N, then 0.79 N, then 3e-3 N, converged in 11
# iterations; measured against the first residual alone it was given up at 0.79 N)
DIVERGENCE_FACTOR = 1e3
# a Newton guess whose constrained dofs lie this close to their values [m] gets them exactly
# (round-off of an extrapolation) and no lifting in its first residual (solve_step)
SNAP_DISTANCE = 1e-12
#: the parts of a Newton solve's time that _ResidualProblem.seconds accumulates
PROFILE_PARTS = ("residual", "tangent", "factorise", "solve")
# significant digits of the constants that decide whether a kept tangent may be kept (solve_step)
TANGENT_KEY_DIGITS = 9
# dolfinx Dirichlet conditions kept per model (solve_step's _dirichlet)
DIRICHLET_CACHE_SIZE = 64
#: C compiler flags of the forms and expressions compiled by FFCx: dolfinx's default
#: ``-O2 -g0`` plus reassociation and reciprocals (no NaN/inf assumptions, compile only: the
#: process's floating-point mode is untouched). The residual kernel of the default liver (P2,
#: 14 points) takes 1.69 ms instead of 2.04 ms, the tangent's 30 ms instead of 32.5 ms; the
#: residual changes by 3e-11 of its largest entry (round-off), the reference's curves by less
#: than the Newton tolerance (docs/fe-reference.md, "Speed")
JIT_PARAMS = {"cffi_extra_compile_args": ["-O2", "-g0", "-fno-math-errno",
                                          "-funsafe-math-optimizations"]}


def configure_linear_solver(ksp: PETSc.KSP) -> None:
    """GMRES preconditioned by a MUMPS factorisation that is kept between Newton iterations.

    The tangent is symmetric (the second derivative of the potential of each step:
    hyperelastic, the Prony history a constant stress, Taylor-Hood's mixed potential, the
    Newmark mass; Dirichlet rows and columns zeroed alike), so the factorisation is MUMPS's
    symmetric-indefinite LDL^T ("cholesky" in PETSc's naming): 2.2 s -> ~1.4 s at 24k
    Taylor-Hood dofs, the same Newton iterates.

    An exact factorisation per iteration (the usual Newton set-up) spends ~80 % of a P2
    iteration on the factorisation (0.1-0.15 s at 5k dofs, against ~0.03 s to assemble
    the tangent and ~3 ms per back-solve). The tangent changes little from one iteration,
    load step or test point to the next (a new indented vertex changes a few rows), so
    an older factorisation is an excellent preconditioner: GMRES converges in a few
    iterations to ``KRYLOV_RTOL``, Newton keeps its quadratic convergence and takes
    the same iterations as with exact solves (measured: identical counts, solutions equal
    to 2e-12 relative), and the factorisation is recomputed only when GMRES slows down.
    """
    ksp.setType("gmres")
    ksp.setGMRESRestart(KRYLOV_MAX_IT)
    ksp.setTolerances(rtol=KRYLOV_RTOL, atol=0.0, max_it=KRYLOV_MAX_IT)
    pc = ksp.getPC()
    pc.setType("cholesky")
    pc.setFactorSolverType("mumps")


class _ResidualProblem(NonlinearProblem):
    """dolfinx's NonlinearProblem plus a known vector added to the residual, a NaN guard, a
    lagged factorisation of the tangent (:func:`configure_linear_solver`) and chord steps.

    Chord steps: near a converged state a Newton iteration (assemble the tangent, 0.3 s at
    24k Taylor-Hood dofs and quadrature degree 4, then GMRES on the kept factorisation, ~10
    back-solves) costs ten times a residual plus one back-solve with the kept factorisation,
    and the tangent hardly changes. So an iteration is such a chord step while the residual
    fell by ``CHORD_CONTRACTION`` or more over the previous iteration, and the first
    iteration of a step is one when the previous step ended so. A slower fall after a chord
    step assembles the tangent and factorises it afresh (the next chord steps then use it);
    Newton iterations otherwise keep the factorisation while GMRES converges fast. Measured
    on the liver punch (vertex 138, 24k dofs, 40-step ramp-and-hold): 301 iterations with 4
    tangents and 4 factorisations in 22.6 s, against 81 iterations with 81 tangents and 2
    (LU) factorisations in 64 s without chord steps. A contraction of 0.5 rather than 0.3
    (245 iterations, 6 factorisations) or 0.7 cuts indentation + relaxation of vertices 138
    and 3 from 88.6 s (0.3) or 83.3 s (0.7) to 81.8 s. The converged state is the same to
    the Newton tolerance: only the path to it changes.
    ``refactor`` (set by :func:`solve_step` when the Dirichlet dofs or the material's
    constants change, and after a failed solve) forces a fresh tangent and factorisation.

    A chord step whose residual is larger than the one it started from is taken back (the
    iterate returns to where it was) and the solve goes on with Newton steps on a fresh
    tangent, without chord steps: the kept factorisation can be that of a much older tangent
    (GMRES converged on it for the whole solve), which near a large rotation or a limit point
    sends the chord step far off (a hanging 1446-vertex figure, Taylor-Hood, 0.25 g from rest:
    residual 3.6e-3 N, then 3.7e-2 N after a chord step, then a diverging oscillation to 7e3 N;
    with Newton steps it converges in 9 iterations). Solves where no chord step makes the
    residual grow take exactly the same iterates as without this rule.
    """

    def __init__(self, residual: ufl.Form, w: fem.Function, jacobian: ufl.Form):
        super().__init__(residual, w, [], J=jacobian, jit_params=JIT_PARAMS)
        self.offset: PETSc.Vec | None = None  # zero on Dirichlet rows (see solve_step)
        self.newton: weakref.ref | None = None  # the Newton solver, set by _newton_solver
        self.refactor = True  # the next tangent is assembled and factorised afresh
        self.lift_first = True  # the first residual of a solve applies dolfinx's lifting
        self.residual_norms: list[float] = []  # of the current solve, one per residual
        self.chord_first = False  # the next solve's first iteration may keep the tangent
        self.tangent_key: tuple | None = None  # what the kept tangent was assembled for
        self.after_chord = False  # the last iteration was a chord step
        self.norm_floor = 0.0  # force norm of the state the solve starts from [N]
        self.chords_off = False  # a chord step of this solve raised the residual
        self.previous: np.ndarray | None = None  # the last accepted iterate of this solve
        self.previous_residual: np.ndarray | None = None  # and its residual vector
        # R(x) without Dirichlet rows and offset at the last residual's iterate, when that
        # residual had no lifting (None otherwise), and that of the last accepted iterate
        self.unconstrained: np.ndarray | None = None
        self.previous_unconstrained: np.ndarray | None = None
        self.plain_residual = False  # the last residual had no lifting (F)
        # Anderson mixing of this solve's chord steps (update): (x - dx, -dx) of the last one
        # and the differences of these between consecutive ones, the last ANDERSON_DEPTH
        self.last_chord: tuple[np.ndarray, np.ndarray] | None = None
        self.mixing_steps: list[tuple[np.ndarray, np.ndarray]] = []
        self.taken_back = 0  # chord steps taken back (performance reports)
        self.factorisations = 0  # over the model's life (performance reports)
        self.assemblies = 0  # tangent assemblies, likewise
        # where the time goes [s], over the model's life (performance reports): residual and
        # tangent assembly, linear solves that factorised afresh, the other linear solves
        self.seconds = dict.fromkeys(PROFILE_PARTS, 0.0)
        self._solve_start = 0.0  # end of the last J (the linear solve follows it)
        self._refreshed = False  # the last J asked for a fresh factorisation
        # the residual form's packed coefficients of this solve (the unknown's entries
        # refreshed per residual, see _coefficients) and where the unknown goes in them
        self._packed: dict | None = None
        # the AIJ copy of a block-assembled tangent that MUMPS factorises (see _newton_solver;
        # None: the tangent itself is factorised) and the tangent last assembled
        self.factored: PETSc.Mat | None = None
        self._solver_matrix: PETSc.Mat | None = None
        self._unknown_gather = _unknown_gather(self.L, w)

    @property
    def krylov(self) -> PETSc.KSP:
        """The Newton solver's linear solver, fetched from it when needed and never kept.

        dolfinx returns ``krylov_solver`` with pybind11's ``reference_internal``: the KSP
        object keeps its NewtonSolver alive, and the NewtonSolver keeps this problem alive
        through the callbacks it holds in C++ (``F``, ``J``, ``P``, ``update``). A KSP kept
        here would close a cycle that Python's garbage collector cannot see, and every model
        (mesh, spaces, forms, solver) would stay in memory after its last use: 38 MB per
        8.9k-dof Taylor-Hood punch model. The solver is held weakly (``newton``) for the same
        reason."""
        return self.newton().krylov_solver

    def chord(self) -> bool:
        """Whether the next iteration is a chord step (class docstring)."""
        norms = self.residual_norms
        if self.refactor or self.chords_off:
            return False
        if len(norms) < 2:
            return self.chord_first
        return (len(norms) <= CHORD_MAX_ITERATIONS
                and norms[-1] <= CHORD_CONTRACTION * norms[-2])

    def J(self, x: PETSc.Vec, A: PETSc.Mat) -> None:
        ksp = self.krylov
        chord = self.chord()
        # a chord step is one back-solve with the kept factorisation, whatever tangent it has
        ksp.setType("preonly" if chord else "gmres")
        self._refreshed = False
        if chord:
            ksp.getPC().setReusePreconditioner(True)
            self.after_chord = True
            self._solve_start = time.perf_counter()
            return
        start = time.perf_counter()
        super().J(x, A)
        self._solver_matrix = A
        A.setOption(PETSc.Mat.Option.SYMMETRIC, True)  # LDL^T reads half of it
        self.assemblies += 1
        # the previous GMRES solve (if any) says whether the kept factorisation still
        # preconditions well; a chord step that fell too slowly says it is too old for chords
        slow = ksp.getIterationNumber() > KRYLOV_REFRESH_IT or ksp.getConvergedReason() < 0
        refresh = self.refactor or slow or self.after_chord
        ksp.getPC().setReusePreconditioner(not refresh)
        self.factorisations += refresh
        self.refactor = self.after_chord = False
        self._refreshed = refresh
        self._solve_start = time.perf_counter()
        self.seconds["tangent"] += self._solve_start - start

    def P(self, x: PETSc.Vec, P: PETSc.Mat) -> None:
        """The matrix MUMPS factorises: the tangent J just assembled, in AIJ format, when it
        is to be factorised afresh (a kept factorisation keeps its matrix)."""
        if not self._refreshed:
            return
        start = time.perf_counter()
        self._solver_matrix.convert("aij", out=P)
        P.setOption(PETSc.Mat.Option.SYMMETRIC, True)
        self._solve_start = time.perf_counter()
        self.seconds["tangent"] += self._solve_start - start

    def update(self, solver: NewtonSolver, dx: PETSc.Vec, x: PETSc.Vec) -> None:
        """Newton's update ``x <- x - dx``; a chord step's is Anderson-mixed (type II, the
        last ``ANDERSON_DEPTH`` chord steps of this solve with the same factorisation)."""
        self.seconds["factorise" if self._refreshed else "solve"] += (time.perf_counter()
                                                                      - self._solve_start)
        if not (self.after_chord and self.plain_residual) or ANDERSON_DEPTH == 0:
            self.restart_mixing()  # a Newton step, or the lifted first residual
            x.axpy(-1.0, dx)
            return
        x_k, f_k = x.array_r.copy(), -dx.array_r
        g_k = x_k + f_k  # the plain chord step's iterate
        last, self.last_chord = self.last_chord, (g_k, f_k)
        if last is None:
            x.axpy(-1.0, dx)
            return
        # only the newest differences are computed: the older ones are kept from before
        self.mixing_steps.append((f_k - last[1], g_k - last[0]))
        del self.mixing_steps[:-ANDERSON_DEPTH]
        d_f = np.array([d[0] for d in self.mixing_steps])
        d_g = np.array([d[1] for d in self.mixing_steps])
        # min |f_k - d_f^T gamma| through its normal equations on unit columns (a 4x4 system:
        # 0.03 ms instead of LAPACK's 0.2 ms on the 5046 x 4 matrix of the default liver)
        norms = np.linalg.norm(d_f, axis=1)
        norms[norms == 0.0] = 1.0
        unit = d_f / norms[:, None]
        gamma = np.linalg.lstsq(unit @ unit.T, unit @ f_k, rcond=None)[0] / norms
        x.array[:] = x_k + f_k - gamma @ d_g

    def restart_mixing(self) -> None:
        """Forget the chord steps mixed so far (the next one starts a new mixing)."""
        self.last_chord = None
        self.mixing_steps.clear()

    def form(self, x: PETSc.Vec) -> None:
        # no ghost update (dolfinx's form): the model is serial, its vectors have no ghosts
        # an inverted element makes J^(-2/3) NaN; stop at once instead of iterating to max_it
        if not np.all(np.isfinite(x.array_r)):
            raise StepFailed("non-finite Newton iterate")

    def F(self, x: PETSc.Vec, b: PETSc.Vec) -> None:
        start = time.perf_counter()
        try:
            self._checked_residual(x, b)
        finally:
            self.seconds["residual"] += time.perf_counter() - start

    def _checked_residual(self, x: PETSc.Vec, b: PETSc.Vec) -> None:
        """F's work: the residual, the taking back of a chord step, the divergence guard."""
        first = not self.residual_norms
        if first:
            self.restart_mixing()
            self._packed = None  # the step's coefficients (history, predictor) are new
        self.plain_residual = not (first and self.lift_first)
        norm = self._residual(x, b, lift=not self.plain_residual)
        norms = self.residual_norms
        if first:
            self.residual_norms.append(norm)
        elif self.after_chord and not norm <= norms[-1]:  # a chord step that made it worse
            x.array[:] = self.previous
            b.array[:] = self.previous_residual
            self.unconstrained = self.previous_unconstrained
            norm = norms[-1]
            self.residual_norms.append(norm)
            self.chords_off = self.refactor = True  # Newton steps on a fresh tangent from here
            self.taken_back += 1
        else:
            self.residual_norms.append(norm)
            # near a limit point (a gravity sag crushing the cells at the clamp's rim) a
            # diverging solve took 11-15 iterations and 7-8 factorisations before it failed;
            # stop it early
            if not norm <= DIVERGENCE_FACTOR * max(norms[0], norms[1], self.norm_floor):
                raise StepFailed(f"diverging Newton iterate (residual {norm:.3g} N, first "
                                 f"{norms[0]:.3g} N)")
        self.previous = x.array.copy()
        self.previous_residual = b.array.copy()
        self.previous_unconstrained = self.unconstrained

    def _coefficients(self, x: PETSc.Vec) -> dict:
        """The residual form's packed coefficients at the iterate ``x``: packed by dolfinx at
        the first residual of a solve; afterwards only the unknown's entries change, and they
        are gathered from ``x`` (0.03 ms instead of 0.25 ms for dolfinx's packing of the
        Prony history and the predictor too, on the default liver)."""
        gather = self._unknown_gather
        if self._packed is None or gather is None:
            self._packed = pack_coefficients(self.L)
        else:
            packed, columns, dofs = gather
            self._packed[packed][:, columns] = x.array_r[dofs]
        return self._packed

    def _residual(self, x: PETSc.Vec, b: PETSc.Vec, *, lift: bool) -> float:
        """Assemble the residual at ``x`` into ``b``; return its norm [N]."""
        self.unconstrained = None
        if lift:
            # the first iterate (the step's guess) misses the Dirichlet values: dolfinx's
            # lifting b -= A (g - x) makes the first Newton update bring them smoothly
            super().F(x, b)
        else:
            # x holds them (from the first update on, or a guess that had them: see
            # solve_step), so the lifting, a tangent of every constrained cell and most of a
            # residual's cost, adds nothing
            assemble_unconstrained(b, self.L, self._coefficients(x))
            # kept: at the converged iterate of a quasi-static step it is the nodal force
            self.unconstrained = b.array_r.copy()
            set_bc(b, self.bcs, x, -1.0)  # the rows' constraint equations, x - g
        if self.offset is not None:
            b.axpy(1.0, self.offset)
        return b.norm()


class FEModel:
    """Function space, compiled forms and Newton solver of one mesh + material + element.

    Built once per process (the constructor compiles the forms); experiments
    change only Dirichlet data, constants and coefficient arrays, through
    :func:`solve_step`. Serial by design (``MPI.COMM_SELF``): the reference
    distributes test points over ranks, not meshes.

    Attributes:
        mesh: the organ's tetrahedral mesh (vertex ids are the project's ids).
        material: instantaneous material (the model applies :func:`long_term` itself).
        fe: element, quadrature degree and Newton settings.
        domain: the dolfinx mesh.
        space: the solution space (vector P1/P2, or mixed P2-P1 for TH, P1-P1 for ANP).
        vertex_dofs: (N, 3) int32, solution-vector index of each mesh vertex's x, y, z
            displacement (P2: the vertex dofs).
        pressure_dofs: (Np,) int32, solution-vector indices of the pressure (TH and ANP, else
            empty).
        n_cells, n_qp: cells and quadrature points per cell of the internal variables.
    """

    def __init__(self, mesh: TetMesh, material: MaterialSection, fe: FESection):
        if fe.element not in ELEMENTS:
            raise ParameterError(f"fe.element = {fe.element!r}: must be one of {ELEMENTS}")
        self.mesh, self.material, self.fe = mesh, check_material(material), fe
        # failed Newton solves are expected (the step is cut) and reported by us, not by
        # dolfinx's C++ log on stderr
        dolfinx.log.set_log_level(dolfinx.log.LogLevel.ERROR)
        cell = ufl.Mesh(ufl.VectorElement("Lagrange", "tetrahedron", 1))
        self.domain = dmesh.create_mesh(MPI.COMM_SELF, mesh.tets, mesh.vertices, cell)
        self._vertex_entity = _vertex_entities(self.domain)
        q = fe.quadrature_degree
        tet = self.domain.ufl_cell()
        self.space = fem.FunctionSpace(self.domain, _element(fe.element, tet))
        self._is_mixed = fe.element in MIXED_ELEMENTS
        self._disp = self.space.sub(0) if self._is_mixed else self.space
        self.vertex_dofs = self._component_dofs(0, self._vertex_entity)
        self.pressure_dofs = (np.unique(self.space.sub(1).dofmap.list.array).astype(np.int32)
                              if self._is_mixed else np.zeros(0, np.int32))

        self.w = fem.Function(self.space)  # the unknown
        self._u_pred = fem.Function(self.space)  # Newmark predictor u_n + dt v_n (u part used)
        quad = ufl.TensorElement("Quadrature", tet, degree=q, quad_scheme="default")
        self._hist = fem.Function(fem.FunctionSpace(self.domain, quad))  # H^n of material.py
        self._qdofs = self._hist.function_space.dofmap.list.array.reshape(-1)
        points, _ = basix.make_quadrature(basix.CellType.tetrahedron, q)
        self.n_cells = self.domain.topology.index_map(3).size_local
        self.n_qp = len(points)
        c = lambda v: fem.Constant(self.domain, PETSc.ScalarType(v))
        self._C10, self._C01, self._gamma, self._c_m = c(0.0), c(0.0), c(1.0), c(0.0)
        self._gravity = fem.Constant(self.domain, np.zeros(3, dtype=PETSc.ScalarType))
        residual, s_iso = balance_of_momentum(self, rho=c(material.density),
                                              kappa=c(material.kappa))
        jacobian = ufl.derivative(residual, self.w, ufl.TrialFunction(self.space))
        self._s_iso_expr = fem.Expression(s_iso, points, jit_params=JIT_PARAMS)
        self._cells = np.arange(self.n_cells, dtype=np.int32)

        self._problem = _ResidualProblem(residual, self.w, jacobian)
        self._residual_vec = fem.petsc.create_vector(self._problem.L)
        self._offset = fem.petsc.create_vector(self._problem.L)
        self._solver = _newton_solver(self._problem, fe.newton_max_it)
        self._dirichlet_cache: dict = {}  # see _dirichlet
        self.newton_iterations = 0  # total over the model's life (performance reports)
        self.newton_solves = 0  # likewise (failed ones included)
        self.n_prony = len(material.prony_g)
        log.debug("FE model: %s, %d dofs, %d cells x %d quadrature points",
                  fe.element, self.n_dofs, self.n_cells, self.n_qp)

    def newton_profile(self) -> dict[str, float]:
        """The Newton work of this model so far (performance reports): solves, iterations,
        tangent assemblies, factorisations and the seconds of each part of
        :data:`PROFILE_PARTS` (``<part>_s``; a factorisation's back-solve counts with it)."""
        p = self._problem
        return {"solves": self.newton_solves, "iterations": self.newton_iterations,
                "tangents": p.assemblies, "factorisations": p.factorisations,
                **{f"{part}_s": seconds for part, seconds in p.seconds.items()}}

    def forget_tangent(self) -> None:
        """Start the next solve from a fresh tangent and factorisation, as a new model would:
        a work item's Newton iterates then never depend on the items computed before it on
        this process, so any distribution of items over ranks gives bit-identical results."""
        problem = self._problem
        problem.refactor, problem.tangent_key, problem.chord_first = True, None, False

    def destroy(self) -> None:
        """Free the model's PETSc matrices and vectors now; the model is unusable afterwards.

        petsc4py (PETSc 3.18) does not destroy an object whose last wrapper Python collects: it
        moves it to its communicator's garbage, freed only by ``PETSc.garbage_cleanup`` on that
        communicator. dolfinx gives each mesh and index map a communicator of its own, which
        goes with the model, so that garbage is never freed: the tangent of every dropped model
        (last held by the problem's wrapper) stayed allocated, 9 MB per 8.9k-dof Taylor-Hood
        punch model. Destroyed here, each object is freed at once, or by the Newton solver when
        it goes if the solver holds it too."""
        problem, solver = self._problem, self._solver
        functions = (self.w, self._u_pred, self._hist)
        for obj in (problem._solver_matrix, problem.factored, solver._A, solver._b,
                    self._residual_vec, self._offset,
                    *(f._petsc_x for f in functions)):  # Function.vector, where it was made
            if obj is not None:
                obj.destroy()

    @property
    def n_dofs(self) -> int:
        """Length of the solution vector."""
        return self.w.x.array.size

    def _component_dofs(self, dim: int, entities: np.ndarray) -> np.ndarray:
        """(len(entities), 3) int32: solution index of each entity's first dof, per component."""
        out = np.empty((len(entities), 3), dtype=np.int32)
        cell_of, local_of = _entity_in_cell(self.domain, dim, entities)
        for k in range(3):
            sub = self._disp.sub(k)
            cell_dofs = sub.dofmap.list.array.reshape(sub.dofmap.list.num_nodes, -1)
            layout = [sub.dofmap.dof_layout.entity_dofs(dim, i)[0]
                      for i in range(_N_ENTITIES[dim])]
            out[:, k] = cell_dofs[cell_of, np.asarray(layout)[local_of]]
        return out

    def clamp_dofs(self, vertices: np.ndarray) -> np.ndarray:
        """(K, 3) int32 dofs held by clamping ``vertices``: their own and, for P2/TH, the
        midpoint dofs of every edge whose two ends are both clamped (a clamped face)."""
        vertices = np.asarray(vertices, dtype=np.int64)
        clamped = np.zeros(self.mesh.n_vertices, dtype=bool)
        clamped[vertices] = True
        return self.surface_patch_dofs(vertices,
                                       self.mesh.edges[clamped[self.mesh.edges].all(axis=1)])

    def surface_patch_dofs(self, vertices: np.ndarray, edges: np.ndarray) -> np.ndarray:
        """(K, 3) int32 dofs of a patch of nodes: the vertices' own and, for P2/TH, the
        mid-edge dofs of ``edges`` (E', 2) vertex pairs (a punch face: every FE node on it)."""
        dofs = self.vertex_dofs[np.asarray(vertices, dtype=np.int64)]
        edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
        if self.fe.element in VERTEX_ELEMENTS or len(edges) == 0:
            return dofs
        edge_ids = _edge_entities(self.domain, self._vertex_entity[edges])
        return np.concatenate([dofs, self._component_dofs(1, edge_ids)])

    def set_history(self, values: np.ndarray) -> None:
        """Store (n_cells, n_qp, 9) tensors [Pa] as the stress term H of the residual form."""
        self._hist.x.array.reshape(-1, 9)[self._qdofs] = values.reshape(-1, 9)

    def isochoric_stress_at_quadrature_points(self) -> np.ndarray:
        """(n_cells, n_qp, 9) S_iso0 [Pa] of the current iterate, at the residual's points."""
        return self._s_iso_expr.eval(self._cells).reshape(self.n_cells, self.n_qp, 9)

    def vertex_values(self, u: np.ndarray) -> np.ndarray:
        """(N, 3) float64: the displacement of every mesh vertex [m] from a solution vector."""
        return u[self.vertex_dofs]


def _element(name: str, tet: ufl.Cell) -> ufl.FiniteElementBase:
    """The UFL element of ``fe.element``: vector P1 or P2, Taylor-Hood (P2 displacement, P1
    pressure) or ANP (P1 displacement, P1 pressure with a lumped pressure mass:
    :func:`pressure_compliance`)."""
    p1 = ufl.VectorElement("Lagrange", tet, 1)
    p2 = ufl.VectorElement("Lagrange", tet, 2)
    pressure = ufl.FiniteElement("Lagrange", tet, 1)
    return {"P1": p1, "P2": p2, "TH": ufl.MixedElement([p2, pressure]),
            "ANP": ufl.MixedElement([p1, pressure])}[name]


def pressure_compliance(element: str, p: ufl.core.expr.Expr, q: ufl.core.expr.Expr,
                        kappa: fem.Constant, dx: ufl.Measure, domain: dmesh.Mesh
                        ) -> ufl.Form:
    """The term ``int p q / kappa`` of a u-p element's pressure equation.

    Taylor-Hood integrates it with the residual's rule ``dx``. ANP (average nodal pressure,
    Bonet and Burton 1998) lumps it: ``sum_a V_a p_a q_a / kappa`` with ``V_a`` the vertex's
    share of its tets' volume (a quarter of each). With ``J`` constant in a P1 tet the pressure
    equation then reads ``p_a = kappa (v_a / V_a - 1)``, ``v_a`` the same share of the deformed
    volume: one pressure per vertex, a function of the vertex displacements alone (the
    pressure dofs are eliminated exactly; the element has the vertex displacements as its
    only degrees of freedom, as the particle model). One volume constraint per vertex instead
    of one per tet (about 3 tets per vertex) is what frees P1 from volumetric locking.

    On a straight tet the lumped product is ``5 int p q (exact) - 4 int p q (centroid rule)``
    for P1 ``p, q`` (consistent mass ``V/20 (1 + delta_ab)``, centroid value the vertices'
    mean), so both terms are standard quadrature degrees 2 and 1: the lumped mass is the
    consistent one plus four times the Dohrmann-Bochev pressure-projection stabilisation.
    """
    if element != "ANP":
        return p * q / kappa * dx
    exact = ufl.dx(domain=domain, metadata={"quadrature_degree": 2})
    centroid = ufl.dx(domain=domain, metadata={"quadrature_degree": 1})
    return 5.0 * p * q / kappa * exact - 4.0 * p * q / kappa * centroid


def second_piola_kirchhoff(model: FEModel, kappa: fem.Constant | float
                           ) -> tuple[ufl.core.expr.Expr, ...]:
    """(u, F, S, S_iso0) of ``model``'s unknown: its displacement part, the deformation
    gradient, the residual's second Piola-Kirchhoff stress ``S`` (module docstring) [Pa] and
    the instantaneous isochoric stress S_iso0 [Pa]; ``kappa`` the bulk modulus [Pa] (used by
    the displacement-only elements' pressure ``kappa (J - 1)``)."""
    if model._is_mixed:
        u, p = ufl.split(model.w)
    else:
        u = model.w
    F = ufl.Identity(3) + ufl.grad(u)
    C = F.T * F
    s_iso = isochoric_stress(C, model._C10, model._C01)
    s_vol = pressure_stress(C, p if model._is_mixed else kappa * (ufl.det(F) - 1.0))
    return u, F, s_vol + model._gamma * s_iso + model._hist, s_iso


def quadrature_measure(model: FEModel) -> ufl.Measure:
    """The cell measure of ``model``'s forms (its quadrature degree, default scheme)."""
    return ufl.dx(domain=model.domain, metadata={"quadrature_degree": model.fe.quadrature_degree,
                                                 "quadrature_scheme": "default"})


def balance_of_momentum(model: FEModel, *, rho: fem.Constant, kappa: fem.Constant
                        ) -> tuple[ufl.Form, ufl.core.expr.Expr]:
    """The residual form R(w; v) of the module docstring on ``model``'s space, constants and
    coefficients, and the instantaneous isochoric stress S_iso0 it uses (evaluated after each
    step for the Prony history).

    Args:
        rho: density [kg/m^3].
        kappa: bulk modulus [Pa] (penalty for P1/P2, the pressure's compliance for TH/ANP).
    """
    if model._is_mixed:
        v, p_test = ufl.TestFunctions(model.space)
        u_pred = ufl.split(model._u_pred)[0]
    else:
        v, u_pred = ufl.TestFunction(model.space), model._u_pred
    u, F, S, s_iso = second_piola_kirchhoff(model, kappa)
    J = ufl.det(F)
    p = ufl.split(model.w)[1] if model._is_mixed else None
    dx = quadrature_measure(model)
    residual = (ufl.inner(F * S, ufl.grad(v)) - rho * ufl.dot(model._gravity, v)
                + rho * model._c_m * ufl.dot(u - u_pred, v)) * dx
    if model._is_mixed:
        residual += ((J - 1.0) * p_test * dx
                     - pressure_compliance(model.fe.element, p, p_test, kappa, dx, model.domain))
    return residual, s_iso


def _newton_solver(problem: _ResidualProblem, max_it: int) -> NewtonSolver:
    """dolfinx's Newton solver on ``problem``: the residual norm decides convergence (its
    tolerance is set per step by :func:`solve_step`), a failure is returned, not raised (the
    step is then cut), linear solves as :func:`configure_linear_solver`."""
    solver = NewtonSolver(MPI.COMM_SELF, problem)
    if problem.a.function_spaces[0].dofmap.index_map_bs > 1:
        # the tangent assembled by 3x3 blocks (BAIJ: 20 ms instead of 30 ms on the default
        # liver, most of AIJ's time went to inserting single entries) and copied to AIJ for
        # MUMPS, whose LDL^T does not take BAIJ (0.4 ms)
        aij, solver._A = solver._A, create_matrix(problem.a, "baij")
        solver.setJ(problem.J, solver._A)
        # dolfinx's C++ setJ references the new matrix without releasing the one it held (the
        # AIJ NewtonSolver made): its reference and the wrapper's are released here, or that
        # matrix is never freed (4.3 MB per 4.6k-dof P2 punch model)
        aij.decRef()
        aij.destroy()
        problem.factored = create_matrix(problem.a)
        solver.setP(problem.P, problem.factored)
    configure_linear_solver(solver.krylov_solver)
    problem.newton = weakref.ref(solver)  # not the KSP: see _ResidualProblem.krylov
    solver.set_update(problem.update)
    solver.convergence_criterion = "residual"
    solver.rtol = 0.0  # see solve_step
    solver.max_it = max_it
    solver.error_on_nonconvergence = False
    return solver


def clamp(dofs: np.ndarray) -> tuple[Constraint, ...]:
    """Constraints holding (K, 3) dofs at zero displacement."""
    return tuple(Constraint(k, dofs[:, k], 0.0) for k in range(3))


def prescribe_dofs(dofs: np.ndarray, displacement: np.ndarray) -> tuple[Constraint, ...]:
    """Constraints moving every node of (K, 3) ``dofs`` by the same ``displacement`` (3,) [m]."""
    return tuple(Constraint(k, dofs[:, k], float(displacement[k])) for k in range(3))


def initial_state(model: FEModel) -> FEState:
    """Undeformed, unstressed, at rest, progress 0."""
    n = model.n_dofs
    return FEState(u=np.zeros(n), velocity=np.zeros(n),
                   history=np.zeros((model.n_prony, model.n_cells, model.n_qp, 9)),
                   s_iso=np.zeros((model.n_cells, model.n_qp, 9)), force=None, progress=0.0)


def _set_material(model: FEModel, state: FEState, dt: float | None) -> tuple[np.ndarray,
                                                                               np.ndarray]:
    """Constants and H for a step of length dt (None: long-term hyperelastic); returns (a, b)."""
    if dt is None:
        m = long_term(model.material)
        model._C10.value, model._C01.value, model._gamma.value = m.C10, m.C01, 1.0
        model._hist.x.array[:] = 0.0
        return np.zeros(0), np.zeros(0)
    m = model.material
    decay, gain = prony_step(m, dt)
    model._C10.value, model._C01.value = m.C10, m.C01
    model._gamma.value = m.long_term_factor + gain.sum()
    model.set_history(np.einsum("i,icqk->cqk", decay, state.history)
                      - gain.sum() * state.s_iso)
    return decay, gain


def assemble_unconstrained(b: PETSc.Vec, form: fem.FormMetaClass,
                           coefficients: dict | None = None) -> None:
    """Assemble the linear ``form`` into ``b`` (zeroed first), no Dirichlet conditions;
    ``coefficients`` packed as :func:`dolfinx.fem.assemble.pack_coefficients` (default: packed
    here)."""
    with b.localForm() as loc:
        loc.set(0.0)
    assemble_vector(b, form, coeffs=coefficients)  # serial (COMM_SELF): no ghosts to add


def _unknown_gather(form: fem.FormMetaClass, unknown: fem.Function
                    ) -> tuple[tuple, np.ndarray, np.ndarray] | None:
    """Where ``unknown``'s entries go in ``form``'s packed coefficients: ``(key, columns,
    dofs)`` with ``packed[key][:, columns] == unknown.x.array[dofs]`` for any values of it, or
    None when the packing is not such a gather (more than one cell integral, or dof
    transformations). Found by packing the unknown set to 1..n, checked on random values."""
    x = unknown.x.array
    saved = x.copy()
    try:
        x[:] = 0.0
        zero = pack_coefficients(form)
        if len(zero) != 1:
            return None
        key = next(iter(zero))
        x[:] = np.arange(1, x.size + 1)
        numbered = pack_coefficients(form)[key]
        columns = np.flatnonzero(np.any(numbered != zero[key], axis=0))
        dofs = np.rint(numbered[:, columns] - zero[key][:, columns]).astype(np.int64) - 1
        if np.any(dofs < 0) or np.any(dofs >= x.size):
            return None
        x[:] = np.random.default_rng(0).standard_normal(x.size)
        if not np.array_equal(pack_coefficients(form)[key][:, columns], x[dofs]):
            return None
        return key, columns, dofs
    finally:
        x[:] = saved


def _assemble_residual(model: FEModel) -> np.ndarray:
    """R(w) without Dirichlet rows, for the current coefficients [N]."""
    assemble_unconstrained(model._residual_vec, model._problem.L)
    return model._residual_vec.array_r.copy()


def solve_step(model: FEModel, state: FEState, load: Load, progress: float, *,
               dt: float | None, inertia: bool = False,
               guess: np.ndarray | None = None) -> FEState:
    """One Newton solve from ``state`` to the equilibrium under ``load``; returns the new state.

    Args:
        progress: the experiment's control variable at the end of the step (stored).
        dt: None for the long-term hyperelastic material (quasi-static tests);
            otherwise a viscoelastic step of ``dt`` seconds (internal variables updated).
        inertia: Newmark average acceleration (beta = 1/4, gamma = 1/2, no numerical
            dissipation) written as the trapezoidal rule, which needs no initial
            acceleration: ``(4/dt^2) M (u1 - u0 - dt v0) + R(u1) + R(u0) = 0`` and
            ``v1 = 2 (u1 - u0)/dt - v0``, where ``R(u0) = -M a0`` is
            :attr:`FEState.force` of the previous step (at rest it is minus the weight:
            ``a0 = g``, consistent).
        guess: initial Newton iterate (default: ``state.u``).

    Raises:
        StepFailed: Newton did not converge (the caller halves the step).
    """
    if inertia and dt is None:
        raise ParameterError("a dynamic step needs a time step dt")
    decay, gain = _set_material(model, state, dt)
    model._gravity.value[:] = load.gravity
    problem = model._problem
    problem.bcs = [_dirichlet(model, c) for c in load.constraints]
    problem.offset = None
    model._c_m.value = 0.0
    if inertia:
        offset = state.force.copy() if state.force is not None else _rest_force(model, state)
        for c in load.constraints:
            offset[c.dofs] = 0.0  # Dirichlet rows hold the constraint equation only
        offset[model.pressure_dofs] = 0.0  # the pressure equation is not time-integrated
        problem.offset = model._offset
        problem.offset.array[:] = offset
        model._u_pred.x.array[:] = state.u + dt * state.velocity
        model._c_m.value = 4.0 / dt ** 2
    # what the tangent's structure depends on besides w: a kept tangent is kept for these only.
    # The constants to TANGENT_KEY_DIGITS significant digits: equal dynamic steps differ in
    # the last bits of dt (t_{k+1} - t_k of a linspace), and a key that saw them refactorised
    # at nearly every step (0.75 factorisations per step of the liver's release)
    key = (tuple((c.component, hash(c.dofs.tobytes())) for c in load.constraints),
           *(float(f"{float(v.value):.{TANGENT_KEY_DIGITS}g}")
             for v in (model._c_m, model._C10, model._C01)))
    if key != problem.tangent_key:
        problem.refactor, problem.tangent_key = True, key
    problem.residual_norms, problem.after_chord, problem.chords_off = [], False, False
    x = model.w.x.array
    x[:] = state.u if guess is None else guess
    # a guess whose constrained dofs are at their values to round-off (an extrapolation in
    # the driving load, a held punch, the clamp) starts without the lifting (F)
    problem.lift_first = False
    for c in load.constraints:
        if np.any(np.abs(x[c.dofs] - c.value) > SNAP_DISTANCE):
            problem.lift_first = True
        else:
            x[c.dofs] = c.value
    # The relative test of dolfinx 0.5's NewtonSolver divides by the first increment's
    # norm (metres), so it is switched off; the force scale enters through atol instead.
    force_scale = 0.0 if state.force is None else float(np.linalg.norm(state.force))
    model._solver.atol = model.fe.newton_atol + model.fe.newton_rtol * force_scale
    problem.norm_floor = force_scale
    try:
        iterations, converged = model._solver.solve(model.w)
    except (StepFailed, RuntimeError) as exc:  # RuntimeError: e.g. MUMPS on a singular matrix
        iterations, converged, reason = 0, False, str(exc)
    else:
        reason = f"no convergence in {iterations} iterations"
    model.newton_iterations += iterations
    model.newton_solves += 1
    if not converged:
        log.debug("Newton failed at progress %.6g: %s", progress, reason)
        # a factorisation that failed (NaN or singular matrix) stays failed in PETSc and
        # would fail every retry; drop it so the halved step starts afresh
        model._solver.krylov_solver.reset()
        configure_linear_solver(model._solver.krylov_solver)
        problem.refactor = True
        raise StepFailed(reason)
    norms = problem.residual_norms
    if len(norms) >= 3:  # the last iteration's fall decides whether the next step starts chord
        problem.chord_first = norms[-1] <= CHORD_CONTRACTION * norms[-2]
    u = model.w.x.array.copy()
    new = FEState(u=u, velocity=state.velocity, history=state.history, s_iso=state.s_iso,
                  force=None, progress=progress)
    if dt is not None:
        s_new = model.isochoric_stress_at_quadrature_points()
        new.history = (decay[:, None, None, None] * state.history
                       + gain[:, None, None, None] * (s_new - state.s_iso)[None])
        new.s_iso = s_new
    if inertia:
        new.velocity = 2.0 * (u - state.u) / dt - state.velocity
    # the nodal force R(u) (c_m = 0, no Dirichlet rows): a quasi-static solve assembled it
    # with its last residual, at this u and with these coefficients (the same numbers); a
    # dynamic one assembled the residual with inertia and offset, so it is assembled again
    kept = problem.unconstrained
    model._c_m.value = 0.0
    new.force = kept if kept is not None and not inertia else _assemble_residual(model)
    return new


def _dirichlet(model: FEModel, c: Constraint) -> fem.DirichletBCMetaClass:
    """The dolfinx condition of ``c``, built once per (component, dofs, value): a march
    prescribes the same clamp at every step and a held punch the same depth for its hold,
    and dolfinx's constructor costs 2-3 ms."""
    key = (c.component, c.dofs.tobytes(), c.value)
    bc = model._dirichlet_cache.get(key)
    if bc is None:
        if len(model._dirichlet_cache) >= DIRICHLET_CACHE_SIZE:
            model._dirichlet_cache.clear()
        bc = model._dirichlet_cache[key] = fem.dirichletbc(
            PETSc.ScalarType(c.value), c.dofs, model._disp.sub(c.component))
    return bc


def _rest_force(model: FEModel, state: FEState) -> np.ndarray:
    """R(u0) of an unstressed state at rest (a dynamic run's start), current gravity."""
    if np.any(state.u) or np.any(state.history) or np.any(state.velocity):
        raise ParameterError("a dynamic run without a stored force must start from rest")
    model.w.x.array[:] = state.u
    return _assemble_residual(model)


def _vertex_entities(domain: dmesh.Mesh) -> np.ndarray:
    """(N,) int32: dolfinx topology vertex of each input (project) vertex id."""
    domain.topology.create_connectivity(3, 0)
    cell_vertices = domain.topology.connectivity(3, 0).array.reshape(-1, 4)
    geometry_nodes = domain.geometry.dofmap.array.reshape(-1, 4)
    inputs = np.asarray(domain.geometry.input_global_indices, dtype=np.int64)
    out = np.full(len(inputs), -1, dtype=np.int32)
    out[inputs[geometry_nodes.ravel()]] = cell_vertices.ravel()
    return out


_N_ENTITIES = {0: 4, 1: 6}  # vertices and edges of a tetrahedron


def _entity_in_cell(domain: dmesh.Mesh, dim: int, entities: np.ndarray) -> tuple[np.ndarray,
                                                                                  np.ndarray]:
    """For each entity, one cell containing it and its local index in that cell."""
    domain.topology.create_connectivity(3, dim)
    c2e = domain.topology.connectivity(3, dim).array.reshape(-1, _N_ENTITIES[dim])
    cells = np.repeat(np.arange(len(c2e)), _N_ENTITIES[dim])
    local = np.tile(np.arange(_N_ENTITIES[dim]), len(c2e))
    first = np.full(int(c2e.max()) + 1, -1, dtype=np.int64)
    first[c2e.ravel()] = np.arange(c2e.size)  # any cell containing the entity will do
    pos = first[np.asarray(entities)]
    return cells[pos], local[pos]


def _edge_entities(domain: dmesh.Mesh, vertex_pairs: np.ndarray) -> np.ndarray:
    """dolfinx edge index of each (topology-vertex) pair."""
    domain.topology.create_entities(1)
    domain.topology.create_connectivity(1, 0)
    e2v = np.sort(domain.topology.connectivity(1, 0).array.reshape(-1, 2), axis=1)
    n = int(e2v.max()) + 1
    keys = e2v[:, 0].astype(np.int64) * n + e2v[:, 1]
    order = np.argsort(keys)
    pairs = np.sort(vertex_pairs, axis=1).astype(np.int64)
    return order[np.searchsorted(keys[order], pairs[:, 0] * n + pairs[:, 1])].astype(np.int32)
