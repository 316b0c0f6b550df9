"""FE reference physics against closed-form and semi-analytic solutions (small meshes, P2 mostly).

The homogeneous solutions below are written independently of the FE code: the
strain energy is a function of the principal stretches and its derivatives are
taken by complex-step differentiation (exact to round-off), not by UFL.
"""

import dataclasses

import numpy as np
import pytest
from scipy.optimize import brentq

pytest.importorskip("dolfinx")

from forcecal.errors import ConvergenceError  # noqa: E402
from forcecal.mesh import TetMesh, box_mesh, check_mesh  # noqa: E402
from forcecal.scene import FESection, MaterialSection  # noqa: E402
from reference_fe import experiments as ex  # noqa: E402
from reference_fe.material import long_term  # noqa: E402
from reference_fe.model import (Constraint, FEModel, FEState, Load, StepFailed,  # noqa: E402
                                clamp, initial_state, solve_step)

pytestmark = pytest.mark.fe

MATERIAL = MaterialSection(prony_tau=(0.2, 1.0))  # C10 2 kPa, C01 1 kPa, kappa 300 kPa
L = 0.01  # block edge [m]


# --- semi-analytic homogeneous solutions of the same strain energy ----------------------------

def energy(stretches, m: MaterialSection, part: str = "all"):
    """W(l1, l2, l3) of the compressible Mooney-Rivlin model (complex-safe)."""
    l1, l2, l3 = stretches
    J = l1 * l2 * l3
    i1 = l1 ** 2 + l2 ** 2 + l3 ** 2
    i2 = (l1 * l2) ** 2 + (l2 * l3) ** 2 + (l3 * l1) ** 2
    w_iso = m.C10 * (J ** (-2 / 3) * i1 - 3) + m.C01 * (J ** (-4 / 3) * i2 - 3)
    w_vol = 0.5 * m.kappa * (J - 1) ** 2
    return {"all": w_iso + w_vol, "iso": w_iso, "vol": w_vol}[part]


def nominal_stress(stretches, m: MaterialSection, part: str = "all") -> np.ndarray:
    """Principal nominal (1st PK) stresses P_i = dW/dl_i [Pa] by complex step."""
    h = 1e-30
    out = np.empty(3)
    for i in range(3):
        s = np.array(stretches, dtype=complex)
        s[i] += 1j * h
        out[i] = energy(s, m, part).imag / h
    return out


def lateral_stretch(stretch: float, m: MaterialSection) -> float:
    """Lateral stretch of a uniaxial test: P_2(stretch, lt, lt) = 0."""
    return brentq(lambda lt: nominal_stress((stretch, lt, lt), m)[1], 0.5, 1.5, xtol=1e-15)


def _pk2(l1: float, l2: float, m: MaterialSection) -> tuple[np.ndarray, np.ndarray]:
    """Principal 2nd PK stresses S_k = (1/l_k) dW/dl_k of stretches (l1, l2, l2) along the axis
    (k = 1) and laterally (k = 2), isochoric and volumetric parts [Pa], by complex step."""
    h = 1e-30
    iso, vol = np.empty(2), np.empty(2)
    for k, s in enumerate(((l1 + 1j * h, l2, l2), (l1, l2 + 1j * h, l2))):
        iso[k] = energy(s, m, "iso").imag / h / (l1, l2)[k]
        vol[k] = energy(s, m, "vol").imag / h / (l1, l2)[k]
    return iso, vol


def viscoelastic_uniaxial(stretch_at, knots: np.ndarray,
                          m: MaterialSection) -> tuple[np.ndarray, np.ndarray]:
    """Viscoelastic uniaxial test of a homogeneous block with traction-free lateral faces.

    Axial stretch ``stretch_at(t)``, lateral stretch l2 = l3 from S_2 = 0, with
    ``S = S_vol + g_inf S_iso0 + sum_i h_i`` and the Prony stresses as the hereditary integral
    ``h_i(t) = g_i int_0^t exp(-(t - s)/tau_i) dS_iso0/ds ds``, evaluated directly (a sum over
    the whole history at every time, not the FE's recursion) on a fine grid: each interval
    between knots split into >= 20 pieces of <= tau_min/100, S_iso0 linear in a piece, the
    kernel at its midpoint (relative error (dt/tau)^2/24 <= 4e-6 per increment).

    Returns, at ``knots``:
        nominal axial stress P_1 = l1 S_1 [Pa];
        bound [Pa] on the error of an FE that steps from knot to knot. Its update is exact for
        an S_iso0 linear within each step, so its h_i integrates the piecewise-linear
        interpolant S^ of S_iso0 through the knots; by parts,
        ``|h_i^FE - h_i| <= g_i/tau_i int exp(-(t - s)/tau_i) |S^ - S_iso0| ds`` per
        component. A lateral error is taken up by l2, which changes S_1 by
        (dS_1/dl2)/(dS_2/dl2) ~ (l2/l1)^2 < 1 times it (both derivatives are dominated by the
        volumetric stress), so the bound is l1 times the sum of both components' bounds (to
        first order: the feedback of l2 into S_iso0 is ~mu0/kappa = 2 % of it).
    """
    g, tau = np.array(m.prony_g), np.array(m.prony_tau)
    edges = np.r_[0.0, knots]
    pieces = [max(20, int(np.ceil((b - a) / (tau.min() / 100)))) for a, b in zip(edges[:-1],
                                                                                  edges[1:])]
    grid = np.concatenate([[0.0]] + [np.linspace(a, b, n + 1)[1:]
                                     for a, b, n in zip(edges[:-1], edges[1:], pieces)])
    mid = 0.5 * (grid[1:] + grid[:-1])
    iso = np.zeros((len(grid), 2))
    axial = np.zeros(len(grid))
    l2 = 1.0
    for n in range(1, len(grid)):
        l1 = stretch_at(grid[n])
        weight = np.sum(g[:, None] * np.exp(-(grid[n] - mid[:n])[None] / tau[:, None]), axis=0)
        history = weight[:-1] @ np.diff(iso[:n], axis=0)  # h_i summed over earlier pieces

        def stress(lateral):
            s_iso, s_vol = _pk2(l1, lateral, m)
            return (s_vol + m.long_term_factor * s_iso + history
                    + weight[-1] * (s_iso - iso[n - 1])), s_iso

        l2 = brentq(lambda lateral: stress(lateral)[0][1], l2 - 0.02, l2 + 0.02, xtol=1e-15)
        s, iso[n] = stress(l2)
        axial[n] = l1 * s[0]
    at = np.searchsorted(grid, knots)
    nodes = np.r_[0, at]
    deviation = sum(np.abs(np.interp(grid, grid[nodes], iso[nodes, k]) - iso[:, k])
                    for k in range(2))
    bound = np.empty(len(knots))
    for j, i in enumerate(at):
        rate = np.sum(g[:, None] / tau[:, None]
                      * np.exp(-(grid[i] - grid[:i + 1])[None] / tau[:, None]), axis=0)
        bound[j] = stretch_at(grid[i]) * np.trapz(rate * deviation[:i + 1], grid[:i + 1])
    return axial[at], bound


# --- meshes and loads ---------------------------------------------------------------------------

def mirrored_block(a: float, h: float) -> TetMesh:
    """2 x 2 x 1 cells of a x a x h, cells mirrored about x = 0 and y = 0: a mesh with the
    two mirror symmetries of the top centre vertex (0, 0, h), unlike the Kuhn box."""
    cell = box_mesh((1, 1, 1), (a, a, h))
    vertices, tets = [], []
    for sx in (1, -1):
        for sy in (1, -1):
            tets.append((cell.tets if sx * sy > 0 else cell.tets[:, [0, 2, 1, 3]])
                        + len(vertices) * cell.n_vertices)
            vertices.append(cell.vertices * [sx, sy, 1])
    v, t = np.concatenate(vertices), np.concatenate(tets)
    keys, inverse = np.unique(np.round(v / a * 1e6).astype(np.int64), axis=0,
                              return_inverse=True)
    merged = np.zeros((len(keys), 3))
    merged[inverse.ravel()] = v
    return check_mesh(TetMesh(merged, inverse.ravel()[t]))


def face(mesh: TetMesh, axis: int, value: float) -> np.ndarray:
    return np.nonzero(np.isclose(mesh.vertices[:, axis], value))[0]


def uniaxial_load(model: FEModel, stretch: float) -> tuple[Load, np.ndarray]:
    """Rollers on x = 0, y = 0, z = 0; x = L moved to stretch * L. Returns (load, x = L dofs)."""
    m = model.mesh
    rollers = [Constraint(k, model.clamp_dofs(face(m, k, 0.0))[:, k], 0.0) for k in range(3)]
    pulled = model.clamp_dofs(face(m, 0, L))[:, 0]
    return Load(tuple(rollers) + (Constraint(0, pulled, (stretch - 1.0) * L),)), pulled


def uniaxial_history(model: FEModel, stretch_at, times, viscous: bool = False) -> list:
    """March a uniaxial block through ``stretch_at(t)``; returns the states at ``times``
    (long-term hyperelastic steps, or viscoelastic ones if ``viscous``)."""
    def step(state, previous, t):
        load, _ = uniaxial_load(model, stretch_at(t))
        return solve_step(model, state, load, t, dt=t - state.progress if viscous else None)

    return list(ex.march(initial_state(model), np.asarray(times), step, max_cuts=4,
                         what="uniaxial block", unit="s"))


@pytest.fixture(scope="module")
def p2_block():
    return FEModel(box_mesh((1, 1, 1), (L, L, L)), MATERIAL, FESection(element="P2"))


@pytest.fixture(scope="module")
def symmetric_block():
    mesh = mirrored_block(L, L)
    top = int(np.argmin(np.linalg.norm(mesh.vertices - [0, 0, L], axis=1)))
    fixed = face(mesh, 2, 0.0)
    model = FEModel(mesh, MATERIAL, FESection(element="P2"))
    return model, fixed, top, mesh.inward_normals([top])[0]


# --- tests ----------------------------------------------------------------------------------

@pytest.mark.parametrize("element", ["P1", "P2", "TH"])
def test_vertex_dofs_and_clamped_face_dofs(element):
    mesh = box_mesh((2, 1, 1), (2 * L, L, L))
    model = FEModel(mesh, MATERIAL, FESection(element=element))
    target = model.w.sub(0) if element == "TH" else model.w
    target.interpolate(lambda x: x)  # displacement field u(X) = X
    np.testing.assert_allclose(model.vertex_values(model.w.x.array), mesh.vertices, atol=1e-15)
    base = face(mesh, 2, 0.0)
    base_edges = mesh.edges[np.isin(mesh.edges, base).all(axis=1)]
    expected = len(base) + (0 if element == "P1" else len(base_edges))  # P2: + edge midpoints
    dofs = model.clamp_dofs(base)
    assert dofs.shape == (expected, 3) and len(np.unique(dofs)) == 3 * expected


def test_material_refuses_a_bad_prony_series_with_the_scene_message():
    """The FE material (used without a scene file too) and the scene loader share the check."""
    from forcecal.errors import ParameterError, SceneError
    from forcecal.scene import replace, scene_from_dict
    from reference_fe.material import check_material

    bad = dataclasses.replace(MATERIAL, prony_g=(0.6, 0.5))
    with pytest.raises(ParameterError, match=r"Prony series: sum\(material.prony_g\) = 1.1 "
                       "must be < 1"):
        check_material(bad)
    with pytest.raises(SceneError, match=r"sum\(material.prony_g\) = 1.1 must be < 1"):
        replace(scene_from_dict({}), material={"prony_g": [0.6, 0.5]})
    with pytest.raises(ParameterError, match="differ in length"):
        check_material(dataclasses.replace(MATERIAL, prony_g=(0.3,)))


def test_isochoric_stress_is_the_derivative_of_the_energy():
    """The written-out S_iso0 equals 2 dW_iso/dC taken by UFL, for a general (non-diagonal,
    volume-changing) deformation: the relative L2 mismatch is round-off."""
    import ufl
    from dolfinx import fem

    from reference_fe.material import isochoric_energy, isochoric_stress

    model = FEModel(box_mesh((1, 1, 1), (L, L, L)), MATERIAL, FESection(element="P2"))
    model.w.interpolate(lambda x: np.stack([0.3 * x[1] ** 2 / L + 0.05 * x[0],
                                            0.2 * x[0] * x[2] / L, -0.1 * x[2] ** 2 / L]))
    F = ufl.Identity(3) + ufl.grad(model.w)
    C = ufl.variable(F.T * F)
    by_ufl = 2 * ufl.diff(isochoric_energy(C, MATERIAL.C10, MATERIAL.C01), C)
    written = isochoric_stress(C, MATERIAL.C10, MATERIAL.C01)
    dx = ufl.dx(metadata={"quadrature_degree": 4})
    error = fem.assemble_scalar(fem.form(ufl.inner(written - by_ufl, written - by_ufl) * dx))
    norm = fem.assemble_scalar(fem.form(ufl.inner(by_ufl, by_ufl) * dx))
    assert norm > 0 and error < 1e-26 * norm


def test_internal_variables_sit_at_the_residual_quadrature_points():
    """Values evaluated at the quadrature points and stored in H are read back by the residual
    form at the same points, in the same order, for an inhomogeneous field (else the Prony
    history of one point would act at another)."""
    import ufl
    from dolfinx import fem

    from reference_fe.material import isochoric_stress

    model = FEModel(box_mesh((2, 2, 2), (L, L, L)), MATERIAL, FESection(element="P2"))
    model.w.interpolate(lambda x: np.stack([0.3 * x[1] ** 2 / L, 0.2 * x[0] * x[2] / L,
                                            0.1 * np.sin(x[0] / L)]))
    model._C10.value, model._C01.value = MATERIAL.C10, MATERIAL.C01
    values = model.isochoric_stress_at_quadrature_points()
    assert np.ptp(values[..., 0]) > 0.1 * np.abs(values[..., 0]).max()  # really inhomogeneous
    model.set_history(values)
    F = ufl.Identity(3) + ufl.grad(model.w)
    s_iso = isochoric_stress(F.T * F, MATERIAL.C10, MATERIAL.C01)
    dx = ufl.dx(metadata={"quadrature_degree": model.fe.quadrature_degree,
                          "quadrature_scheme": "default"})
    mismatch = fem.assemble_scalar(fem.form(ufl.inner(model._hist - s_iso,
                                                      model._hist - s_iso) * dx))
    scale = fem.assemble_scalar(fem.form(ufl.inner(s_iso, s_iso) * dx))
    assert mismatch < 1e-24 * scale


@pytest.mark.parametrize("element", ["P1", "P2", "TH"])
@pytest.mark.parametrize("stretch", [1.2, 0.85])
def test_uniaxial_stretch_matches_homogeneous_solution(element, stretch):
    """Static (long-term) uniaxial stretch/compression of a cube with roller BCs.

    The exact solution is homogeneous, hence in every element's space, and its
    constant stress satisfies the weak form exactly: the FE solution equals it
    to Newton tolerance (1e-10 N on forces of ~0.1 N), so 1e-7 relative is a
    strict but safe bound (far tighter than the 1 % the task allows).
    """
    model = FEModel(box_mesh((1, 1, 1), (L, L, L)), MATERIAL, FESection(element=element))
    final = uniaxial_history(model, lambda t: 1.0 + (stretch - 1.0) * t, [0.25, 0.5, 0.75, 1.0])
    _, pulled = uniaxial_load(model, stretch)
    force = final[-1].force[pulled].sum()

    m = long_term(MATERIAL)
    lt = lateral_stretch(stretch, m)
    expected = nominal_stress((stretch, lt, lt), m)[0] * L ** 2
    assert force == pytest.approx(expected, rel=1e-7)
    u = model.vertex_values(final[-1].u)
    side = face(model.mesh, 1, L)
    np.testing.assert_allclose(u[side, 1], (lt - 1.0) * L, rtol=1e-7)


@pytest.mark.parametrize("case", ["step", "steps of tau1"])
def test_relaxation_matches_the_hereditary_integral(p2_block, case):
    """Uniaxial stretch to 1.1 then hold, P2, viscoelastic, free lateral faces, against the
    independent semi-analytic solution of :func:`viscoelastic_uniaxial`.

    ``step``: stretch applied in 1e-4 s (2 steps), held 5 tau_max with 60 geometrically
    growing steps (dt/tau1 from 2.5e-4 to 4). ``steps of tau1``: a 1 s ramp then a hold to 3 s,
    every step dt = tau1 (the default scene's ramp runs at dt/tau1 = 0.1): the Prony update is
    exact only for a stress linear in a step, so these large steps test its decay and gain.

    Tolerance: the time-discretisation bound that function returns (observed 0.89 and 0.73 of
    it: 3.8e-6 and 1.3e-3 relative), plus 1e-6 for the Newton tolerance (1e-8) and the
    reference's own quadrature (doubling its substeps changes it by < 1e-9). A Prony gain
    b_i = g_i instead of g_i (1 - exp(-dt/tau_i)) tau_i/dt fails both (errors 9.6e-5, 0.18).
    """
    stretch = 1.1
    if case == "step":
        ramp, times = 1e-4, np.unique(np.r_[5e-5, np.geomspace(1e-4, 5.0, 60)])
    else:
        tau1 = MATERIAL.prony_tau[0]
        ramp, times = 1.0, tau1 * np.arange(1, 16)
    stretch_at = lambda t: 1.0 + (stretch - 1.0) * min(t / ramp, 1.0)  # noqa: E731
    states = uniaxial_history(p2_block, stretch_at, times, viscous=True)
    _, pulled = uniaxial_load(p2_block, stretch)
    fe = np.array([s.force[pulled].sum() / L ** 2 for s in states])  # nominal stress [Pa]

    reference, bound = viscoelastic_uniaxial(stretch_at, times, MATERIAL)
    assert np.all(np.abs(fe - reference) <= bound + 1e-6 * np.abs(reference))
    if case == "step":
        assert np.max(np.abs(fe / reference - 1.0)) < 1e-5
        # the force relaxes from the instantaneous towards the long-term value (ratio 1/g_inf)
        assert fe[1] / fe[-1] > 2.4


def test_long_term_material_is_the_slow_ramp_limit(symmetric_block):
    """A viscoelastic ramp 1e4 x tau_max long ends at the static long-term force.

    The viscous overstress of a ramp of duration T is about sum(g_i tau_i) /
    (g_inf T) ~ 1e-4 of the force here, so 5e-4 is the bound.
    """
    model, fixed, top, normal = symmetric_block
    m = long_term(MATERIAL)
    assert (m.C10, m.C01, m.kappa) == (0.4 * MATERIAL.C10, 0.4 * MATERIAL.C01, MATERIAL.kappa)
    assert m.prony_g == ()
    depth = 0.1 * L
    static = ex.indentation_curve(model, fixed, top, normal, [depth / 2, depth])[-1]
    t_ramp = 1e4 * max(MATERIAL.prony_tau)
    times = t_ramp * np.arange(1, 11) / 10
    slow = ex.relaxation_curve(model, fixed, top, normal, times, depth * times / t_ramp)[-1]
    assert slow @ normal == pytest.approx(static @ normal, rel=5e-4)
    assert slow @ normal > static @ normal  # the remaining overstress is positive


def test_indentation_force_sign_and_symmetry(symmetric_block):
    """Top-centre indentation of a mirror-symmetric block: force along the normal only."""
    model, fixed, top, normal = symmetric_block
    np.testing.assert_allclose(normal, [0, 0, -1], atol=1e-12)
    depths = np.linspace(0.05, 0.2, 4) * L
    force = ex.indentation_curve(model, fixed, top, normal, depths)
    f_n = force @ normal
    assert np.all(f_n > 0) and np.all(np.diff(f_n) > 0)  # pushes in, resists more with depth
    tangential = np.linalg.norm(force - np.outer(f_n, normal), axis=1)
    # mirror symmetry makes it zero; what remains is round-off and Newton residual (< 1e-10 N)
    assert np.all(tangential < 1e-9 * f_n)


def test_gravity_reactions_carry_the_weight(p2_block):
    """Static sag of a block clamped at its base: the base reactions sum to minus the weight."""
    model = p2_block
    base = face(model.mesh, 2, 0.0)
    g = np.array([0.0, 0.0, -9.81])
    state = initial_state(model)
    held = clamp(model.clamp_dofs(base))
    for factor in (0.5, 1.0):
        state = solve_step(model, state, Load(held, factor * g), factor, dt=None)
    support = state.force[model.clamp_dofs(base)].sum(axis=0)  # force applied by the support
    weight = MATERIAL.density * L ** 3 * g
    # balanced to Newton's tolerance: it stops once the residual of the free dofs is below
    # 1e-8 of the force scale (chord steps stop just below it; observed 6e-9 of the weight,
    # and 2e-10 of it in the horizontal components, which the weight does not load)
    np.testing.assert_allclose(support, -weight, rtol=1e-7, atol=1e-8 * np.abs(weight).max())


def test_newmark_conserves_energy_without_viscosity():
    """Undamped average acceleration on a hyperelastic block dropped under gravity.

    With no Prony terms nothing dissipates; the trapezoidal rule conserves
    kinetic + strain + gravity potential energy up to its O(dt^2) error on the
    nonlinear forces (exactly for a linear system). Observed: 3e-5 of the peak
    kinetic energy over 200 steps (about three periods of the first mode); bound 1e-3.
    """
    import ufl
    from dolfinx import fem

    elastic = dataclasses.replace(MATERIAL, prony_g=(), prony_tau=())
    model = FEModel(box_mesh((1, 1, 2), (L, L, 2 * L)), elastic, FESection(element="P2"))
    base = face(model.mesh, 2, 0.0)
    g = np.array([0.0, 0.0, -9.81])
    load = Load(clamp(model.clamp_dofs(base)), g)
    u, v = fem.Function(model.space), fem.Function(model.space)
    F = ufl.Identity(3) + ufl.grad(u)
    C = F.T * F
    J, i1 = ufl.det(F), ufl.tr(C)
    i2 = 0.5 * (i1 ** 2 - ufl.tr(C * C))
    w = (elastic.C10 * (J ** (-2 / 3) * i1 - 3) + elastic.C01 * (J ** (-4 / 3) * i2 - 3)
         + 0.5 * elastic.kappa * (J - 1) ** 2)
    rho = elastic.density
    energy_form = fem.form((w + 0.5 * rho * ufl.dot(v, v) - rho * ufl.dot(ufl.as_vector(g), u))
                           * ufl.dx(metadata={"quadrature_degree": model.fe.quadrature_degree}))
    kinetic_form = fem.form(0.5 * rho * ufl.dot(v, v) * ufl.dx)

    state, energies, kinetic = initial_state(model), [], []
    dt = 2.5e-4  # ~60 steps per period of the block's first mode (~15 ms)
    for k in range(1, 201):
        state = solve_step(model, state, load, k * dt, dt=dt, inertia=True)
        u.x.array[:], v.x.array[:] = state.u, state.velocity
        energies.append(fem.assemble_scalar(energy_form))
        kinetic.append(fem.assemble_scalar(kinetic_form))
    assert max(kinetic) > 0
    assert np.max(np.abs(energies)) < 1e-3 * max(kinetic)


def test_failed_step_is_halved_and_retried(symmetric_block):
    """One 5 mm step (half the block height) with at most 6 Newton iterations fails; halving
    makes it converge, and the end state is the one a finely stepped curve reaches."""
    model, fixed, top, normal = symmetric_block
    tight = FEModel(model.mesh, MATERIAL, FESection(element="P2", newton_max_it=6,
                                                    max_step_cuts=4))
    depth = 0.5 * L
    cut = ex.indentation_curve(tight, fixed, top, normal, [depth])
    fine = ex.indentation_curve(model, fixed, top, normal, np.linspace(0.05, 0.5, 10) * L)
    # same equilibrium reached by two load paths: equal to Newton tolerance (hyperelastic)
    np.testing.assert_allclose(cut[-1], fine[-1], rtol=1e-7, atol=1e-10)


def test_a_failed_factorisation_does_not_poison_the_next_solve(p2_block):
    """Gravity on an unsupported block: singular tangent, MUMPS fails. PETSc keeps a failed
    factorisation failed, so without a reset every halved retry would fail too."""
    model = p2_block
    g = np.array([0.0, 0.0, -9.81])
    with pytest.raises(StepFailed):
        solve_step(model, initial_state(model), Load((), g), 1.0, dt=None)
    held = clamp(model.clamp_dofs(face(model.mesh, 2, 0.0)))
    state = solve_step(model, initial_state(model), Load(held, g), 1.0, dt=None)
    assert np.all(np.isfinite(state.u)) and np.abs(state.u).max() > 0


def test_unrecoverable_step_raises_convergence_error_naming_the_step(symmetric_block):
    model, fixed, top, normal = symmetric_block
    no_cuts = FEModel(model.mesh, MATERIAL, FESection(element="P2", newton_max_it=6,
                                                      max_step_cuts=0))
    with pytest.raises(ConvergenceError, match=rf"indentation of vertex {top}: step 1/1 "
                       r"\(to 0\.005 m\)"):
        ex.indentation_curve(no_cuts, fixed, top, normal, [0.5 * L])


def test_a_kept_factorisation_and_chord_steps_change_nothing_but_the_cost(monkeypatch):
    """GMRES on an older LU (configure_linear_solver) and chord steps (_ResidualProblem)
    against exact Newton, a fresh tangent and LU at every iteration: the same relaxation
    curve, far fewer tangents and factorisations."""
    import reference_fe.model as fe_model

    mesh = mirrored_block(L, L)
    top = int(np.argmin(np.linalg.norm(mesh.vertices - [0, 0, L], axis=1)))
    fixed, normal = face(mesh, 2, 0.0), mesh.inward_normals([top])[0]
    times = np.r_[np.linspace(0.05, 0.2, 4), 0.2 + 0.3 * np.cumsum(np.ones(6))]
    depths = 0.2 * L * np.minimum(times / 0.2, 1.0)

    def run() -> tuple[np.ndarray, int, int, int]:
        model = FEModel(mesh, MATERIAL, FESection(element="P2"))
        curve = ex.relaxation_curve(model, fixed, top, normal, times, depths)
        return (curve, model.newton_iterations, model._problem.assemblies,
                model._problem.factorisations)

    kept, iterations, assemblies, factorisations = run()
    monkeypatch.setattr(fe_model, "KRYLOV_REFRESH_IT", -1)  # refresh before every solve
    monkeypatch.setattr(fe_model, "CHORD_CONTRACTION", 0.0)  # no chord steps
    fresh, fresh_iterations, fresh_assemblies, fresh_factorisations = run()
    assert fresh_factorisations == fresh_assemblies == fresh_iterations  # exact Newton
    assert assemblies < fresh_iterations / 2
    assert factorisations <= fresh_iterations // 4
    # both converge to the same Newton tolerance (1e-8 of the force scale), so the curves agree
    # to it: the hold's guesses (creep_guess) are fitted to each run's own converged states,
    # so the two runs stop at different iterates within it (1.05e-9 of the largest force)
    np.testing.assert_allclose(kept, fresh, rtol=0, atol=1e-8 * np.abs(fresh).max())


def test_a_chord_step_that_raises_the_residual_is_taken_back(monkeypatch):
    """A large step after a small one starts with a chord step on the small step's
    factorisation (nearly the rest tangent): its residual grows, it is taken back and the
    solve goes on with Newton steps, ending where exact Newton ends (Newton tolerance)."""
    import reference_fe.model as fe_model

    mesh = mirrored_block(L, L)
    top = int(np.argmin(np.linalg.norm(mesh.vertices - [0, 0, L], axis=1)))
    fixed, normal = face(mesh, 2, 0.0), mesh.inward_normals([top])[0]
    depths = np.array([0.05, 0.45]) * L

    def run() -> tuple[np.ndarray, int]:
        model = FEModel(mesh, MATERIAL, FESection(element="P2"))
        curve = ex.indentation_curve(model, fixed, top, normal, depths)
        return curve, model._problem.taken_back

    kept, taken_back = run()
    assert taken_back == 1
    monkeypatch.setattr(fe_model, "KRYLOV_REFRESH_IT", -1)
    monkeypatch.setattr(fe_model, "CHORD_CONTRACTION", 0.0)
    exact, none_taken = run()
    assert none_taken == 0
    np.testing.assert_allclose(kept, exact, rtol=0, atol=1e-7 * np.abs(exact).max())


def _block_ramp_and_hold() -> tuple:
    """A punch-like ramp-and-hold on the mirrored block: (mesh, top vertex, fixed vertices,
    its inward normal, times [s], depths [m]): a 0.2 s ramp to 0.1 L in 4 steps, then 4 hold
    steps of 0.3 s."""
    mesh = mirrored_block(L, L)
    top = int(np.argmin(np.linalg.norm(mesh.vertices - [0, 0, L], axis=1)))
    fixed, normal = face(mesh, 2, 0.0), mesh.inward_normals([top])[0]
    times = np.r_[np.linspace(0.05, 0.2, 4), 0.2 + 0.3 * np.cumsum(np.ones(4))]
    depths = 0.1 * L * np.minimum(times / 0.2, 1.0)
    return mesh, top, fixed, normal, times, depths


def test_a_guess_that_holds_the_constraints_starts_without_the_lifting(monkeypatch):
    """solve_step's first residual applies dolfinx's lifting only when the guess misses a
    prescribed value: on a punch-like ramp-and-hold the first step from rest (its guess is
    the rest state), not the extrapolated ramp steps or the hold. Forcing the lifting on
    every step (SNAP_DISTANCE < 0) gives the same curve to round-off."""
    import reference_fe.model as fe_model
    from dolfinx.fem.petsc import NonlinearProblem

    mesh, top, fixed, normal, times, depths = _block_ramp_and_hold()
    lifted = []
    lifting_residual = NonlinearProblem.F

    def counted(self, x, b):
        lifted.append(1)
        lifting_residual(self, x, b)

    monkeypatch.setattr(NonlinearProblem, "F", counted)
    # Anderson mixing starts at a solve's first residual without lifting, so with it the
    # two paths would differ at the Newton tolerance, not in round-off
    monkeypatch.setattr(fe_model, "ANDERSON_DEPTH", 0)

    def run() -> tuple[np.ndarray, int]:
        lifted.clear()
        model = FEModel(mesh, MATERIAL, FESection(element="P2"))
        curve = ex.relaxation_curve(model, fixed, top, normal, times, depths)
        return curve, len(lifted)

    snapped, n_snapped = run()
    monkeypatch.setattr(fe_model, "SNAP_DISTANCE", -1.0)
    lifting, n_lifting = run()
    assert n_snapped == 1 and n_lifting >= len(times)
    # the two paths differ in the first residual's round-off only (the lifting term is
    # A (g - x) = 0 there); the Newton tolerance is 1e-8 of the force scale
    np.testing.assert_allclose(snapped, lifting, rtol=0, atol=1e-10 * np.abs(lifting).max())


def test_a_quasi_static_step_s_force_is_its_last_residual(monkeypatch):
    """solve_step takes a quasi-static step's nodal force from its last Newton residual
    (assembled without Dirichlet rows, kept before the rows' constraint equations are set)
    instead of assembling R(u) once more: the same numbers, bit for bit, on a ramp-and-hold
    (viscoelastic) and an indentation (long-term material)."""
    import reference_fe.model as fe_model

    mesh, top, fixed, normal, times, depths = _block_ramp_and_hold()
    pairs = []
    solve = fe_model.solve_step

    def checked(model, state, load, progress, **kwargs):
        new = solve(model, state, load, progress, **kwargs)
        pairs.append((new.force, fe_model._assemble_residual(model)))
        return new

    monkeypatch.setattr(ex, "solve_step", checked)
    model = FEModel(mesh, MATERIAL, FESection(element="P2"))
    ex.relaxation_curve(model, fixed, top, normal, times, depths)
    ex.indentation_curve(model, fixed, top, normal, depths[:4])
    assert len(pairs) == len(times) + 4
    for kept, assembled in pairs:
        assert np.array_equal(kept, assembled)


def test_a_held_step_is_guessed_from_the_creep_of_the_step_before(monkeypatch):
    """extrapolate: linear in the drive while it changes; in a hold, the last change
    extrapolated in time and scaled by ``held``, the held dofs unmoved. A relaxation curve
    guessed that way (HELD_EXTRAPOLATION) is the one guessed from the last state, to the
    Newton tolerance."""
    def state(progress: float, u) -> FEState:
        u = np.asarray(u, dtype=float)
        return FEState(u=u, velocity=0 * u, history=np.zeros(0), s_iso=np.zeros(0),
                       force=None, progress=progress)

    depth = lambda t: min(t, 1.0)  # noqa: E731  (ramp to 1 at t = 1, then held)
    ramp = ex.extrapolate(state(0.5, [0.5, 2.0]), state(0.25, [0.25, 1.0]), depth, 0.75)
    np.testing.assert_allclose(ramp, [0.75, 3.0])
    previous, last = state(2.0, [1.0, 1.0]), state(3.0, [1.0, 1.5])
    np.testing.assert_allclose(ex.extrapolate(last, previous, depth, 5.0), [1.0, 1.5])
    np.testing.assert_allclose(ex.extrapolate(last, previous, depth, 5.0, held=0.8),
                               [1.0, 1.5 + 0.8 * 2.0 * 0.5])

    mesh = mirrored_block(L, L)
    top = int(np.argmin(np.linalg.norm(mesh.vertices - [0, 0, L], axis=1)))
    fixed, normal = face(mesh, 2, 0.0), mesh.inward_normals([top])[0]
    times = np.r_[np.linspace(0.05, 0.2, 4), 0.2 + 0.1 * np.cumsum(1.3 ** np.arange(10))]
    depths = 0.1 * L * np.minimum(times / 0.2, 1.0)

    def curve() -> np.ndarray:
        model = FEModel(mesh, MATERIAL, FESection(element="P2"))
        return ex.relaxation_curve(model, fixed, top, normal, times, depths)

    guessed = curve()
    monkeypatch.setattr(ex, "HELD_EXTRAPOLATION", 0.0)
    last_state = curve()
    np.testing.assert_allclose(guessed, last_state, rtol=0,
                               atol=1e-8 * np.abs(last_state).max())


def test_the_hold_guess_reproduces_a_creep_in_its_functions_exactly():
    """creep_guess interpolates the held states with a constant, the Prony exponentials and a
    quadratic: a displacement history made of these functions is extrapolated exactly (to
    round-off, 1e-12 of its size) from 5 states at the hold's growing time steps; with fewer
    than 3 states there is no fit (the caller extrapolates linearly)."""
    taus = np.array([0.5, 10.0])
    rng = np.random.default_rng(1)
    coefficients = rng.standard_normal((5, 7))  # 5 functions x 7 dofs

    def creep(t: float) -> np.ndarray:
        functions = np.array([1.0, np.exp(-t / 10.0), np.exp(-t / 0.5), t, t * t])
        return functions @ coefficients

    times = 0.5 + np.cumsum(0.06 * 1.19 ** np.arange(6))  # a hold's steps, last as the target
    states = [FEState(u=creep(t), velocity=np.zeros(7), history=np.zeros(0), s_iso=np.zeros(0),
                      force=None, progress=t) for t in times[:-1]]
    guess = ex.creep_guess(states, times[-1], taus)
    np.testing.assert_allclose(guess, creep(times[-1]), rtol=0,
                               atol=1e-12 * np.abs(creep(times[-1])).max())
    assert ex.creep_guess(states[:2], times[-1], taus) is None
