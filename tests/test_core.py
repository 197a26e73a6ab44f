"""Core pipeline: closed-form cases, constraint residuals, certificates, end-to-end solves."""

import numpy as np
import pytest

import sphere_nlp
from sphere_nlp.certify import certify, signed_solid_angles, spherical_angles
from sphere_nlp.connectivity import build_connectivity, validate_mesh
from sphere_nlp.shapes import cylinder, icosphere, octahedron, tetrahedron
from sphere_nlp.targets import MODES
from sphere_nlp.unfold import half_chords_squared

from conftest import MODELS


@pytest.mark.parametrize("shape, angle", [(tetrahedron, 2 * np.pi / 3), (octahedron, np.pi / 2)])
@pytest.mark.parametrize("formulation", ["substituted", "faithful", "log-chord"])
def test_regular_tilings_closed_form(shape, angle, formulation):
    # Equal angles on a regular polyhedron: the optimum is the regular spherical tiling.
    r = sphere_nlp.parameterize(shape(), target="equal-angles", formulation=formulation)
    t = len(r.faces)
    np.testing.assert_allclose(r.angles, angle, atol=1e-10)
    np.testing.assert_allclose(r.excess, 4 * np.pi / t, atol=1e-10)
    assert r.objective < 1e-16      # the optimum is 0; IPOPT stops at tol 1e-8 on the gradient
    assert r.certificate.valid
    np.testing.assert_allclose(signed_solid_angles(r.vertices, r.faces), 4 * np.pi / t, atol=1e-12)


def test_half_chord_formula_matches_cosine_rule():
    rng = np.random.default_rng(2)
    # Random valid spherical triangles from random points.
    P = rng.normal(size=(200, 3, 3))
    P /= np.linalg.norm(P, axis=2, keepdims=True)
    F = np.arange(600).reshape(200, 3)
    X = P.reshape(-1, 3)
    keep = signed_solid_angles(X, F) > 0
    angles = spherical_angles(X, F)[keep]
    opposite = np.stack([np.arccos(np.clip(np.einsum("ij,ij->i", X[F[keep, (j + 1) % 3]],
                                                      X[F[keep, (j + 2) % 3]]), -1, 1))
                         for j in range(3)], axis=1)
    np.testing.assert_allclose(half_chords_squared(angles), np.sin(opposite / 2) ** 2, atol=1e-12)


@pytest.mark.parametrize("mode", MODES)
def test_cylinder_every_mode_certified(mode):
    r = sphere_nlp.parameterize(str(MODELS / "cylinder.off"), target=mode)
    assert r.certificate.valid and r.certificate.flipped == 0
    assert abs(r.certificate.degree - 1) < 1e-9
    assert r.max_constraint_violation <= 1e-8
    assert r.max_angle_error <= 1e-6
    # Solved angles and excesses are consistent with (6) and the Gauss-Bonnet total area.
    np.testing.assert_allclose(r.angles.sum(1) - np.pi, r.excess, atol=1e-8)
    assert abs(r.excess.sum() - 4 * np.pi) < 1e-8


def test_original_angles_on_a_sphere_are_nearly_exact():
    # A fine icosphere is almost a sphere: its spherical map must keep its angles nearly unchanged.
    V, F = icosphere(3)
    r = sphere_nlp.parameterize((V, F), target="original-angles")
    from sphere_nlp.geometry import corner_angles
    assert np.abs(r.angles - corner_angles(V, F)).max() < 0.02
    assert r.certificate.valid


def test_certificate_detects_flip_and_norm_error():
    V, F = octahedron()
    X = V.copy()
    X[4] = [0, 0, -0.2]                      # pull the north pole through: triangles flip
    X[4] /= np.linalg.norm(X[4])
    cert = certify(X, F)
    assert not cert.valid and cert.flipped > 0
    cert = certify(V * 1.001, F)
    assert not cert.valid and "unit sphere" in cert.reason


def test_validate_repairs_orientation():
    V, F = cylinder()
    F[[3, 10]] = F[[3, 10], ::-1]
    V2, F2, c, repairs = validate_mesh(V, F)
    assert repairs == ["flipped 2 face(s) to make the orientation consistent"]
    np.testing.assert_array_equal(F2, cylinder()[1])


def test_shipped_cylinder_is_regenerated_by_code(tmp_path):
    from sphere_nlp.shapes import write_models

    write_models(tmp_path)
    assert (tmp_path / "cylinder.off").read_text() == (MODELS / "cylinder.off").read_text()


def test_tiny_triangles_keep_their_angles():
    # A valid triangulation with a triangle ~1e-5 across and needles of angle ~8e-6 rad around it:
    # the unfold and the angle measurement must not lose their digits (dot products near 1 would;
    # they gave errors of 1e-3 rad here). Smaller still, the walk's placement of a tiny cluster from
    # large neighbours limits accuracy to about 1e-16 / size^2.
    from sphere_nlp.unfold import unfold

    V, F = icosphere(2)
    V = V.copy()
    k = F[0]
    centre = V[k].mean(0)
    V[k] = centre + 1e-5 * (V[k] - centre)          # shrink one triangle to ~1e-5 across
    V /= np.linalg.norm(V, axis=1, keepdims=True)
    c = build_connectivity(F, len(V))
    angles = spherical_angles(V, F)
    excess = signed_solid_angles(V, F)
    assert excess.min() < 1e-10 and certify(V, F).valid
    X, info = unfold(c, angles, excess=excess)
    assert certify(X, F).valid
    assert np.abs(spherical_angles(X, F) - angles).max() < 1e-6


def test_cross_is_numpys_bit_for_bit():
    from sphere_nlp.geometry import cross

    rng = np.random.default_rng(0)
    for shape_u, shape_v in [((500, 3), (500, 3)), ((40, 3, 3), (40, 3, 3)), ((3,), (500, 3)), ((20, 1, 3), (1, 6, 3))]:
        u = rng.normal(size=shape_u) * 10.0 ** rng.integers(-30, 30, size=shape_u)
        v = rng.normal(size=shape_v)
        assert np.array_equal(cross(u, v), np.cross(u, v))


def test_edges_come_sorted_once_each_with_their_two_faces():
    V, F = icosphere(3)
    F = F[np.random.default_rng(1).permutation(len(F))]
    c = build_connectivity(F, len(V))
    pairs = np.sort(np.concatenate([F[:, [1, 2]], F[:, [2, 0]], F[:, [0, 1]]]), axis=1)
    assert np.array_equal(c.edges, np.unique(pairs, axis=0))
    for k in (0, 1):          # each edge's faces hold both its vertices
        assert (np.sort(F[c.edge_faces[:, k]], axis=1)[:, :, None] == c.edges[:, None, :]).any(1).all()


def test_a_results_summaries_are_computed_once_and_handed_out_as_copies():
    V, F = cylinder()
    r = sphere_nlp.parameterize((V, F))
    first = r.usability()
    first["qc_max"] = -1.0
    assert r.usability()["qc_max"] >= 1.0
    assert r.usability()["mean_abs_log_area"] == r.distortion()["mean_abs_log_area"]
