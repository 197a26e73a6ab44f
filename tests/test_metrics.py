"""Distortion metrics against closed-form cases: identity, similarity, known stretch, flips, area sums."""

import json

import numpy as np
from scipy.spatial.transform import Rotation

from sphere_nlp.certify import signed_solid_angles
from sphere_nlp.metrics import (SUMMARY_KEYS, angle_distortion, area_log_ratio, corner_angles,
                                distortion_summary, normalised_areas_3d, per_vertex_mean,
                                quasi_conformal_ratio)
from sphere_nlp.shapes import icosphere, octahedron


def central_projection(V):
    return V / np.linalg.norm(V, axis=1, keepdims=True)


def test_inscribed_octahedron_onto_itself_has_no_distortion():
    V, F = octahedron()
    np.testing.assert_allclose(corner_angles(V, F), np.pi / 3, atol=1e-15)
    np.testing.assert_allclose(angle_distortion(V, V, F), 0, atol=1e-15)
    np.testing.assert_allclose(quasi_conformal_ratio(V, V, F), 1, atol=1e-14)
    np.testing.assert_allclose(area_log_ratio(V, V, F), 0, atol=1e-14)
    s = distortion_summary(V, V, F)
    assert s["valid"] and s["flipped"] == 0 and abs(s["degree"] - 1) < 1e-14
    assert s["mean_abs_angle_diff_deg"] < 1e-12 and s["qc_max"] - 1 < 1e-12
    assert abs(s["min_spherical_angle_deg"] - 90) < 1e-12     # octants: right spherical angles
    assert s["area_cv"] < 1e-14


def test_stretched_octahedron_has_the_closed_form_distortion():
    # Octahedron with apexes at z = +-2, mapped to its central projection (the regular octahedron).
    # Each face is isosceles, base sqrt 2 and legs sqrt 5; its image is equilateral with side sqrt 2.
    V, F = octahedron()
    W = V * [1, 1, 2]
    S = central_projection(W)
    apex = np.arccos(4 / 5)                        # cos = (a - c).(b - c) / |a - c|^2 = 4 / 5
    base = np.arccos(1 / np.sqrt(10))              # cos = (b - a).(c - a) / (sqrt 2 sqrt 5)
    expected = np.abs(np.pi / 3 - np.where(np.abs(W[F][..., 2]) == 2, apex, base))
    np.testing.assert_allclose(angle_distortion(W, S, F), expected, atol=1e-14)
    # In the frame of the base the map is diag(1, sqrt(3/2) / height) with height sqrt(2 ** 2 + 1/2).
    np.testing.assert_allclose(quasi_conformal_ratio(W, S, F), np.sqrt(3), rtol=1e-13)
    np.testing.assert_allclose(area_log_ratio(W, S, F), 0, atol=1e-14)   # all 8 faces still equal


def test_uniform_scaling_and_rotation_is_conformal():
    rng = np.random.default_rng(1)
    V, F = icosphere(2)
    V = V * (1 + 0.1 * rng.random((len(V), 1)))          # a bumpy mesh, not a sphere
    image = 3.7 * Rotation.random(random_state=rng).apply(V)
    assert angle_distortion(V, image, F).max() < 1e-12
    np.testing.assert_allclose(quasi_conformal_ratio(V, image, F), 1, atol=1e-10)


def test_single_triangle_stretch_gives_its_stretch_factor_in_any_orientation():
    V = np.array([[0, 0, 1], [1, 0, 1], [0.3, 0.8, 1]], float)
    F = np.array([[0, 1, 2]])
    rng = np.random.default_rng(2)
    for factor in (1.5, 2.0, 10.0):
        for axis in ([1, factor, 1], [factor, 1, 1]):
            image = Rotation.random(random_state=rng).apply(V * axis)
            rotated_back = Rotation.align_vectors([[0, 0, 1]], [image.mean(axis=0)])[0]
            image = rotated_back.apply(image)          # keep it facing away from the origin
            np.testing.assert_allclose(quasi_conformal_ratio(V, image, F), factor, rtol=1e-12)


def test_reflection_preserves_angles_but_every_triangle_counts_as_flipped():
    V, F = icosphere(1)
    mirrored = V * [-1, 1, 1]
    assert angle_distortion(V, mirrored, F).max() < 1e-12          # planar angles cannot see it
    assert np.isinf(quasi_conformal_ratio(V, mirrored, F)).all()
    assert np.isnan(area_log_ratio(V, mirrored, F)).all()
    s = distortion_summary(V, mirrored, F)
    assert not s["valid"] and s["flipped"] == len(F)
    assert s["qc_mean"] is None and s["qc_max"] is None and s["mean_abs_log_area"] is None
    assert s["min_spherical_angle_deg"] < 0


def test_a_folded_vertex_flips_exactly_the_triangles_certify_counts():
    V, F = icosphere(2)
    S = V.copy()
    vertex = 0
    neighbour = F[np.any(F == vertex, axis=1)][0]
    neighbour = neighbour[neighbour != vertex][0]
    S[vertex] = central_projection((2 * S[neighbour] - S[vertex])[None])[0]   # past its neighbour
    flipped = ~(signed_solid_angles(S, F) > 0)
    assert 0 < flipped.sum() < 7
    qc = quasi_conformal_ratio(V, S, F)
    np.testing.assert_array_equal(np.isinf(qc), flipped)
    np.testing.assert_array_equal(~np.isfinite(area_log_ratio(V, S, F)), flipped)
    s = distortion_summary(V, S, F)
    assert s["flipped"] == flipped.sum() and not s["valid"]
    assert s["qc_max"] == qc[~flipped].max()           # the summary averages the unflipped rest
    json.dumps(s, allow_nan=False)                     # JSON-safe even for a broken map


def test_area_ratios_are_consistent_with_the_total_area():
    V, F = icosphere(2)
    W = V * [1, 1, 2.5]
    S = central_projection(W)
    share = normalised_areas_3d(W, F)
    ratio = np.exp(area_log_ratio(W, S, F))
    # Spherical areas of a valid map sum to 4 pi, and so do the normalised 3D areas.
    np.testing.assert_allclose(share.sum(), 4 * np.pi, rtol=1e-14)
    np.testing.assert_allclose((share * ratio).sum(), 4 * np.pi, rtol=1e-12)
    assert ratio.min() < 1 < ratio.max()               # the poles shrink, the waist grows
    s = distortion_summary(W, S, F)
    omega = share * ratio
    np.testing.assert_allclose(s["area_cv"], omega.std() / omega.mean(), rtol=1e-10)
    np.testing.assert_allclose(s["mean_abs_log_area"], np.abs(np.log(ratio)).mean(), rtol=1e-12)


def test_summary_keys_and_types():
    V, F = icosphere(1)
    s = distortion_summary(V * [1, 2, 3], V, F)
    assert tuple(s) == SUMMARY_KEYS
    assert type(s["valid"]) is bool and type(s["flipped"]) is int
    assert all(type(s[k]) is float for k in SUMMARY_KEYS[2:])
    assert s["qc_mean"] <= s["qc_max"] and s["mean_abs_angle_diff_deg"] <= s["max_abs_angle_diff_deg"]


def test_needle_angles_keep_relative_accuracy():
    epsilon = 1e-9
    V = np.array([[0, 0, 0], [1, 0, 0], [1, epsilon, 0]], float)
    angles = corner_angles(V, np.array([[0, 1, 2]]))[0]
    np.testing.assert_allclose(angles[0], np.arctan(epsilon), rtol=1e-12)
    np.testing.assert_allclose(angles.sum(), np.pi, rtol=1e-15)


def test_per_vertex_mean_skips_flipped_faces():
    faces = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 1]])
    values = per_vertex_mean(faces, np.array([1.0, np.inf, 3.0]), 5)
    np.testing.assert_allclose(values[:4], [2, 2, 1, 3])
    assert np.isnan(values[4])
