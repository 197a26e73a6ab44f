"""Baselines: Alexa's relaxation, the FLASH conformal map, cMCF and the Tutte projection."""

import numpy as np
import pytest

from conftest import shared_mesh
from sphere_nlp.baselines import (alexa_relaxation, beltrami_coefficient, cmcf_map, conformal_map,
                                  cotan_laplacian, linear_beltrami_solver, tutte_projection)
from sphere_nlp.certify import certify
from sphere_nlp.mesh_io import load_mesh
from sphere_nlp.metrics import quasi_conformal_ratio
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


def bumpy_ellipsoid(subdivisions=4):
    """A smooth genus-0 surface that is far from round (so no map is trivially conformal)."""
    V, F = icosphere(subdivisions)
    return V * [1, 1, 2] + 0.2 * np.sin(3 * V[:, [1, 2, 0]]), F


def planar_grid(k=6):
    """A (k+1) x (k+1) grid of the unit square, counter-clockwise triangles, and its boundary vertices."""
    x, y = np.meshgrid(np.linspace(0, 1, k + 1), np.linspace(0, 1, k + 1))
    points = np.c_[x.ravel(), y.ravel()]
    index = np.arange((k + 1) ** 2).reshape(k + 1, k + 1)
    a, b, c, d = index[:-1, :-1].ravel(), index[:-1, 1:].ravel(), index[1:, 1:].ravel(), index[1:, :-1].ravel()
    faces = np.r_[np.c_[a, b, c], np.c_[a, c, d]]
    boundary = np.flatnonzero((points == 0).any(axis=1) | (points == 1).any(axis=1))
    return points, faces, boundary


def test_cotan_laplacian_gives_the_dirichlet_energy_of_the_coordinates():
    # Each coordinate function's gradient on a face is the projection of that axis onto the face,
    # so the three energies add up to sum(area * trace(projection)) = 2 * total area.
    V, F = bumpy_ellipsoid(2)
    K = cotan_laplacian(V, F)
    assert abs(K - K.T).max() < 1e-12 and np.abs(K @ np.ones(len(V))).max() < 1e-12
    area = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1).sum()
    np.testing.assert_allclose(np.einsum("ij,ij->", V, K @ V), 2 * area, rtol=1e-12)


def test_beltrami_coefficient_of_a_stretch_is_its_closed_form():
    points, faces, _ = planar_grid()
    surface = np.c_[points, np.zeros(len(points))]
    np.testing.assert_allclose(beltrami_coefficient(points, faces, 3 * surface), 0, atol=1e-13)
    # (x, y) -> (2x, y): mu = (K - 1) / (K + 1) = 1/3 with K = 2.
    np.testing.assert_allclose(beltrami_coefficient(points, faces, surface * [2, 1, 0]), 1 / 3, atol=1e-13)


def test_linear_beltrami_solver_reproduces_the_affine_map_with_that_coefficient():
    # An affine map has constant mu and solves the equation exactly: pinning the boundary to it
    # must give it back inside.
    points, faces, boundary = planar_grid()
    stretched = points * [2, 1]
    mu = np.full(len(faces), 1 / 3, dtype=complex)
    solved = linear_beltrami_solver(points, faces, mu, boundary, stretched[boundary])
    np.testing.assert_allclose(solved, stretched, atol=1e-12)


def test_conformal_map_is_valid_and_nearly_conformal_on_a_smooth_surface():
    V, F = bumpy_ellipsoid()
    X = conformal_map(V, F)
    assert certify(X, F).valid
    qc = quasi_conformal_ratio(V, X, F)
    assert qc.mean() < 1.05
    # Central projection of the same surface is valid too but far less conformal.
    assert qc.mean() < quasi_conformal_ratio(V, V / np.linalg.norm(V, axis=1, keepdims=True), F).mean()


def test_south_pole_step_removes_the_distortion_around_the_big_triangle():
    V, F = bumpy_ellipsoid()
    corrected = quasi_conformal_ratio(V, conformal_map(V, F), F)
    # Pinning every vertex turns the south-pole step into the identity: the plain harmonic map.
    harmonic_only = quasi_conformal_ratio(V, conformal_map(V, F, fixed_fraction=1.0), F)
    assert corrected.max() < 0.6 * harmonic_only.max()


def test_cmcf_flows_to_a_conformal_sphere():
    V, F = bumpy_ellipsoid()
    X = cmcf_map(V, F)
    assert certify(X, F).valid
    qc = quasi_conformal_ratio(V, X, F)
    assert qc.mean() < 1.05
    # Too few steps leave the surface unround, and the central projection is less conformal.
    assert qc.mean() < quasi_conformal_ratio(V, cmcf_map(V, F, steps=1, time_step=0.01), F).mean()


def test_tutte_projection_is_valid_by_construction():
    V, F = cylinder()
    assert certify(tutte_projection(V, F), F).valid
    V, F = load_mesh(shared_mesh("knight.off"))      # limbs: the case the other baselines fold on
    assert certify(tutte_projection(V, F), F).valid


@pytest.mark.parametrize("method", [conformal_map, cmcf_map, tutte_projection])
def test_baselines_return_unit_vectors_in_input_order(method):
    V, F = cylinder()
    X = method(V, F)
    assert X.shape == V.shape
    np.testing.assert_allclose(np.linalg.norm(X, axis=1), 1, atol=1e-12)
    # Faces keep their orientation: the map has degree +1, not -1.
    assert abs(certify(X, F).degree - 1) < 1e-9
