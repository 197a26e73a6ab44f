"""Starting points (sphere_nlp.starts): the linear guess and the Mobius gauge of the valid start."""

import numpy as np
import pytest

from sphere_nlp.certify import certify, signed_solid_angles
from sphere_nlp.connectivity import build_connectivity
from sphere_nlp import starts
from sphere_nlp.solve import constraint_residuals
from sphere_nlp.starts import linear_initial_guess
from sphere_nlp.targets import MODES, make_targets

from meshgen import ellipsoid


@pytest.mark.parametrize("mode", MODES)
def test_linear_initial_guess_satisfies_linear_constraints(mode):
    V, F = ellipsoid(2)
    c = build_connectivity(F, len(V))
    angles, excess = linear_initial_guess(c, make_targets(mode, V, F, c.vertex_degree))
    res = constraint_residuals(c, angles, excess)
    assert np.abs(res["triangle"]).max() < 1e-12
    assert np.abs(res["vertex"]).max() < 1e-12


def test_excess_gauge_is_stationary_for_sum_of_squared_excesses_and_stays_valid():
    from sphere_nlp import solve
    from sphere_nlp.certify import certify, signed_solid_angles
    from sphere_nlp.embedding import excess_gauge, mobius_centre

    V, F = ellipsoid(2, axes=(1.0, 3.0, 0.4))
    c = build_connectivity(F, len(V))
    area_centred, _ = starts.starting_positions(c, V)
    pushed = mobius_centre(area_centred, np.where(area_centred[:, 0] > 0, 30.0, 1.0))  # off-centre
    moved = excess_gauge(pushed, F)

    def weighted_mean(X):     # the gradient of sum(e^2) over Mobius boosts, up to a factor
        e = signed_solid_angles(X, F)
        centres = X[F].sum(1)
        centres /= np.linalg.norm(centres, axis=1, keepdims=True)
        return (e * e) @ centres / (e @ e), e @ e

    (g_before, f_before), (g_after, f_after) = weighted_mean(pushed), weighted_mean(moved)
    assert certify(moved, F).valid
    assert f_after < f_before and np.linalg.norm(g_before) > 0.04
    assert np.linalg.norm(g_after) < 0.2 * np.linalg.norm(g_before)   # first order only on coarse meshes
