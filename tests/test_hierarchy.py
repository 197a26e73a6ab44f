"""Starting a solve from given sphere positions, and carrying a coarse solution to a subdivision."""

import numpy as np
import pytest
import trimesh

import sphere_nlp
from sphere_nlp import errors
from sphere_nlp.certify import certify
from sphere_nlp.hierarchy import prolong_to_subdivision
from sphere_nlp.shapes import cylinder, icosphere
from sphere_nlp.solve import max_constraint_violation
from sphere_nlp.connectivity import build_connectivity

from meshgen import ellipsoid


def input_positions(result):
    """The result's sphere positions, one row per input vertex."""
    return result.vertices[result.vertex_map]


def test_prolongation_places_geodesic_midpoints_and_certifies():
    V, F = cylinder()
    coarse = sphere_nlp.parameterize((V, F), target="original-areas", start="conformal")
    fine_V, fine_F = trimesh.remesh.subdivide_loop(V, F, iterations=1)
    X = prolong_to_subdivision(input_positions(coarse), fine_F)
    assert certify(X, fine_F).valid
    np.testing.assert_array_equal(X[:len(V)], input_positions(coarse))
    np.testing.assert_allclose(np.linalg.norm(X, axis=1), 1.0, atol=1e-15)
    # every new vertex is equidistant (on the sphere) from its edge's two ends, which lie on its great circle
    new = np.arange(len(V), len(fine_V))
    for v in new[:20]:
        ends = sorted({u for f in fine_F[(fine_F == v).any(1)] for u in f if u < len(V)})
        assert len(ends) == 2
        a, b = X[ends[0]], X[ends[1]]
        assert abs(X[v] @ a - X[v] @ b) < 1e-14
        assert abs(np.linalg.det(np.array([a, b, X[v]]))) < 1e-14


def test_prolongation_refuses_a_mesh_that_is_not_a_subdivision():
    V, F = icosphere(2)
    # icosphere(2) is icosphere(1) subdivided (42 coarse vertices first), not a subdivision of its first 20
    prolong_to_subdivision(V[:42], F)
    with pytest.raises(ValueError, match="not a 1-to-4 subdivision"):
        prolong_to_subdivision(V[:20], F)


def test_subdivided_mesh_solved_from_its_coarse_solution():
    # The hierarchy in the area modes: the fine solve from the carried-over coarse optimum is a
    # certified optimum satisfying (6)-(8).
    V, F = ellipsoid(2)
    coarse = sphere_nlp.parameterize((V, F), target="original-areas", start="conformal")
    fine_V, fine_F = trimesh.remesh.subdivide_loop(V, F, iterations=1)
    start = prolong_to_subdivision(input_positions(coarse), fine_F)
    fine = sphere_nlp.parameterize((fine_V, fine_F), target="original-areas", start=start)
    assert fine.success and fine.certificate.valid and fine.start == "given"
    connectivity = build_connectivity(fine.faces, len(fine.vertices))
    assert max_constraint_violation(connectivity, fine.angles, fine.excess) < 1e-8


@pytest.mark.parametrize("mode", ["original-angles", "equal-areas"])
def test_restart_from_a_solution_stays_there(mode):
    V, F = ellipsoid(2)
    # The NLP's own optimum (start="conformal": without the area modes' authalic route).
    first = sphere_nlp.parameterize((V, F), target=mode, start="conformal")
    again = sphere_nlp.parameterize((V, F), target=mode, start=input_positions(first))
    assert again.success and again.start == "given"
    assert again.objective == pytest.approx(first.objective, rel=1e-6)
    np.testing.assert_allclose(again.angles, first.angles, atol=1e-4)


def test_start_positions_are_checked():
    V, F = ellipsoid(1)
    good = sphere_nlp.parameterize((V, F), target="original-angles")
    with pytest.raises(errors.UsageError, match="the start has 3 positions, the mesh 42 vertices"):
        sphere_nlp.parameterize((V, F), start=np.zeros((3, 3)))
    mirrored = input_positions(good) * np.array([-1.0, 1.0, 1.0])      # every triangle flipped
    with pytest.raises(errors.UsageError, match="not a valid spherical map"):
        sphere_nlp.parameterize((V, F), start=mirrored)
    with pytest.raises(errors.UsageError, match="not a valid spherical map"):
        sphere_nlp.parameterize((V, F), start=2 * input_positions(good))
