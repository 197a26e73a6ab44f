"""Alexa's relaxation baseline: convergence, certificate, and the guard against collapse."""

import numpy as np

from sphere_nlp.baselines import alexa_relaxation
from sphere_nlp.shapes import cylinder, icosphere


def test_alexa_relaxation_maps_cylinder_validly_from_either_start():
    V, F = cylinder()
    for start in ("central", "normals"):
        result = alexa_relaxation(V, F, start=start)
        assert result.converged and result.certificate.valid
        np.testing.assert_allclose(np.linalg.norm(result.positions, axis=1), 1, atol=1e-12)


def test_recentring_prevents_collapse_from_asymmetric_start():
    # Without a guard, plain (uniform-weight) relaxation slides every vertex into one point once the
    # start is not perfectly symmetric; subtracting the mean each sweep keeps the map spread out.
    V, F = cylinder()
    start = V + 0.05 * np.random.default_rng(0).standard_normal(V.shape)
    collapsed = alexa_relaxation(V, F, start=start, edge_length_weights=False, recentre=False)
    guarded = alexa_relaxation(V, F, start=start, edge_length_weights=False, recentre=True)
    assert not collapsed.certificate.valid
    assert np.linalg.norm(collapsed.positions.mean(axis=0)) > 0.99       # all in one spot
    assert guarded.certificate.valid


def test_alexa_relaxation_reports_non_convergence_honestly():
    V, F = icosphere(2)
    result = alexa_relaxation(V * [1, 1, 2], F, max_iter=3)
    assert result.iterations == 3 and not result.converged and result.last_move > 0
