"""The user-facing parts: texture coordinates and textured OBJ, pictures, progress and summary, README."""

import dataclasses

import numpy as np
import pytest

import sphere_nlp
from sphere_nlp.shapes import cylinder, icosphere, octahedron
from sphere_nlp.texture import checker, pole_triangles, spherical_uv, uv_signed_areas

from conftest import MODELS


@pytest.fixture(scope="module")
def cylinder_result():
    """The shipped cylinder mapped with the default target (a fraction of a second)."""
    return sphere_nlp.parameterize(str(MODELS / "cylinder.off"))


def random_rotation(rng):
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def read_textured_obj(path):
    """Positions, uv list, and per face the (v, vt) index pairs (0-based) of an OBJ with ``f v/vt``."""
    positions, uvs, faces = [], [], []
    for line in path.read_text().splitlines():
        words = line.split()
        if not words:
            continue
        if words[0] == "v":
            positions.append([float(w) for w in words[1:4]])
        elif words[0] == "vt":
            uvs.append([float(w) for w in words[1:3]])
        elif words[0] == "f":
            faces.append([[int(i) - 1 for i in corner.split("/")] for corner in words[1:]])
    return np.array(positions), np.array(uvs), np.array(faces)


# --- texture coordinates -----------------------------------------------------------------------------

def check_uv_layout(corner_uv, faces):
    """Every uv triangle counter-clockwise (none mirrored or wrapped around the seam), v in [0, 1]."""
    assert corner_uv.shape == (len(faces), 3, 2)
    areas = uv_signed_areas(corner_uv)
    assert (areas > 0).all(), "uv triangle %d is flipped or wraps around the seam" % np.argmin(areas)
    assert corner_uv[..., 1].min() >= 0 and corner_uv[..., 1].max() <= 1
    assert corner_uv[..., 0].min() >= 0 and corner_uv[..., 0].max() < 2
    return areas


def test_uv_tiles_the_texture_once_under_any_rotation(cylinder_result):
    rng = np.random.default_rng(0)
    V, F = icosphere(3)
    for _ in range(20):
        areas = check_uv_layout(spherical_uv(V @ random_rotation(rng).T, F), F)
        # The uv triangles cover the unit square once: a seam-wrapping triangle alone would add about
        # its height times 1, a mirrored one would cancel area. (Straight uv edges of curved images
        # lose a few per cent near the poles.)
        assert 0.9 < areas.sum() < 1.02
    X, F = cylinder_result.vertices, cylinder_result.faces
    for _ in range(20):
        areas = check_uv_layout(spherical_uv(X @ random_rotation(rng).T, F), F)
        assert 0.6 < areas.sum() < 1.02          # coarser: 168 triangles, some large near the poles


def test_uv_is_longitude_and_latitude_away_from_seam_and_poles():
    V, F = icosphere(2)
    uv = spherical_uv(V, F)
    lon = np.arctan2(V[F, 1], V[F, 0])
    lat = np.arcsin(np.clip(V[F, 2], -1, 1))
    np.testing.assert_allclose(uv[..., 1], lat / np.pi + 0.5, atol=1e-12)
    plain = (np.ptp(uv[..., 0], axis=1) < 0.4) & (np.abs(lat) < 1.2).all(axis=1)
    assert plain.sum() > len(F) // 2
    np.testing.assert_allclose(np.mod(uv[plain, :, 0], 1), np.mod(lon[plain] / (2 * np.pi) + 0.5, 1),
                               atol=1e-12)


def test_seam_triangles_are_shifted_and_pole_corners_take_the_mean():
    V, F = octahedron()        # poles at vertices 4 (north) and 5 (south); vertex 1 is on the seam
    uv = spherical_uv(V, F)
    for i, face in enumerate(F):
        for j, vertex in enumerate(face):
            if vertex in (4, 5):
                others = [k for k in range(3) if k != j]
                assert uv[i, j, 0] == pytest.approx(uv[i, others, 0].mean())
                assert uv[i, j, 1] == (1.0 if vertex == 4 else 0.0)
    # The same vertex gets different u in different triangles only at the seam (u and u + 1) and at
    # the poles.
    for vertex in range(4):
        us = uv[..., 0][F == vertex]
        assert set(np.round(np.mod(us, 1), 12)) == {round(np.mod(us[0], 1), 12)}
    check_uv_layout(uv, F)


def test_pole_inside_a_triangle_still_gives_a_counter_clockwise_uv_triangle():
    V, F = icosphere(1)
    # Turn the sphere so the north pole is the centre of face 0.
    centre = V[F[0]].mean(axis=0)
    centre /= np.linalg.norm(centre)
    axis = np.cross(centre, [0, 0, 1.0])
    angle = np.arccos(centre[2])
    axis /= np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    R = np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K
    X = V @ R.T
    assert 0 in pole_triangles(X, F)
    check_uv_layout(spherical_uv(X, F), F)


def test_checker_repeats_with_the_texture():
    uv = np.random.default_rng(1).random((100, 2))
    np.testing.assert_array_equal(checker(uv), checker(uv + [1, 0]))
    assert set(checker(uv)) == {0, 1}


# --- OBJ with texture coordinates ----------------------------------------------------------------------

def test_obj_output_carries_seam_safe_texture_coordinates(cylinder_result, tmp_path):
    out = tmp_path / "cyl.obj"
    cylinder_result.write(out)
    positions, uvs, corners = read_textured_obj(out)
    X, F = cylinder_result.vertices, cylinder_result.faces
    np.testing.assert_array_equal(positions, X)                  # positions are the sphere, bit for bit
    np.testing.assert_array_equal(corners[..., 0], F)            # faces and vertex order unchanged
    assert len(X) <= len(uvs) < 3 * len(F)                       # shared where they agree
    corner_uv = uvs[corners[..., 1]]
    np.testing.assert_allclose(corner_uv, cylinder_result.texture_coordinates(), atol=1e-8)
    check_uv_layout(corner_uv, F)
    # Our own reader and trimesh both read it back.
    V2, F2 = sphere_nlp.load_mesh(out)
    np.testing.assert_array_equal(F2, F)
    import trimesh

    loaded = trimesh.load(str(out), process=False)
    assert loaded.visual.uv is not None and len(loaded.faces) == len(F)


def test_textured_input_has_input_positions_and_sphere_uv(cylinder_result, tmp_path):
    out = tmp_path / "cyl_textured.obj"
    cylinder_result.write_textured_input(out)
    positions, uvs, corners = read_textured_obj(out)
    V, _ = cylinder()
    np.testing.assert_allclose(positions, V, atol=1e-15)
    np.testing.assert_allclose(uvs[corners[..., 1]], cylinder_result.texture_coordinates(), atol=1e-8)
    with pytest.raises(sphere_nlp.UsageError):
        cylinder_result.write_textured_input(tmp_path / "cyl.ply")
    assert not (tmp_path / "cyl.ply").exists()


def test_ply_and_off_keep_sphere_positions_without_uv(cylinder_result, tmp_path):
    for name in ("s.ply", "s.off"):
        cylinder_result.write(tmp_path / name)
        X, F = sphere_nlp.load_mesh(tmp_path / name)
        np.testing.assert_array_equal(X, cylinder_result.vertices)
    with pytest.raises(sphere_nlp.UsageError):
        sphere_nlp.write_mesh(tmp_path / "t.ply", *octahedron(), spherical_uv(*octahedron()))


def test_uncertified_results_write_nothing(cylinder_result, tmp_path):
    bad = dataclasses.replace(cylinder_result, certificate=dataclasses.replace(
        cylinder_result.certificate, valid=False, reason="1 flipped or degenerate triangle(s)"))
    for write, name in ((bad.write, "s.obj"), (bad.write_textured_input, "t.obj")):
        with pytest.raises(sphere_nlp.CertificateError, match="refusing"):
            write(tmp_path / name)
    assert list(tmp_path.iterdir()) == []
