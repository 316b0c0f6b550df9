"""The discretisation study on the tiny scene (one point): the expected orderings, and the
uniform refinement it relies on."""

import numpy as np
import pytest

pytest.importorskip("dolfinx")

from forcecal.mesh import box_mesh  # noqa: E402
from forcecal.problem import build_problem  # noqa: E402
from forcecal.scene import load_scene  # noqa: E402
from reference_fe.sensitivity import discretisation_study, refine_uniformly  # noqa: E402
from tests.conftest import SCENES  # noqa: E402

pytestmark = pytest.mark.fe


def test_uniform_refinement_keeps_vertices_and_volume():
    coarse = box_mesh((2, 1, 1), (0.02, 0.01, 0.01))
    fine = refine_uniformly(coarse)
    assert fine.n_tets == 8 * coarse.n_tets
    assert fine.n_vertices == coarse.n_vertices + len(coarse.edges)  # + one per edge midpoint
    assert fine.signed_volumes.sum() == pytest.approx(coarse.signed_volumes.sum(), rel=1e-12)
    kept = (np.abs(fine.vertices[None] - coarse.vertices[:, None]).max(axis=2) < 1e-15).any(1)
    assert kept.all()


def test_discretisation_study_orders_the_elements_as_theory_says():
    scene = load_scene(SCENES / "tiny.toml")
    problem = build_problem(scene)
    study = discretisation_study(scene, points=problem.calibration[:1], problem=problem,
                                 quadrature_degrees=(2, 4))
    force = {k: v["indentation_force_N"][0] for k, v in study["variants"].items()}
    assert set(force) == {"P2 q=2", "P2 q=4", "P1 q=4", "TH q=4", "P2 q=4 refined"}
    assert all(f > 0 for f in force.values())
    # P1 tets lock for a nearly incompressible material; P2 still partly (kappa/mu_inf = 125)
    assert force["P1 q=4"] > force["P2 q=4"] > force["TH q=4"]
    # a point indentation softens with refinement (the continuum limit of a point load is 0)
    assert force["P2 q=4 refined"] < force["P2 q=4"]
    # under-integration changes the force, but by percents, not more
    assert abs(study["relative_to_scene_fe"]["P2 q=2"]["force"][0]) < 0.05
    assert study["relative_to_scene_fe"]["P2 q=4"]["force"] == [0.0]
    assert all(v["max_sag_m"] > 0 for v in study["variants"].values())


def test_the_variants_are_shared_out_over_the_ranks_with_the_refined_one_alone_on_rank_0():
    from reference_fe.sensitivity import variant_rank

    kinds = ["coarse"] * 5 + ["refined"]
    assert [variant_rank(w, i, 1) for i, w in enumerate(kinds)] == [0] * 6
    assert [variant_rank(w, i, 2) for i, w in enumerate(kinds)] == [1] * 5 + [0]
    assert [variant_rank(w, i, 3) for i, w in enumerate(kinds)] == [1, 2, 1, 2, 1, 0]
