"""Repaired and reported, then solved: soups, duplicates, unreferenced vertices, orientation, scale,
slivers. The vertex numbering convention (``vertex_map``) is checked on every repair that changes it.
"""

import numpy as np
import pytest

import sphere_nlp
from sphere_nlp.certify import certify
from sphere_nlp.cli import main
from sphere_nlp.mesh_io import load_mesh, write_mesh
from sphere_nlp.repair import prepare_mesh
from sphere_nlp.shapes import icosphere

import meshgen


@pytest.fixture(scope="module")
def ellipsoid_result():
    """The reference run: the ellipsoid as given (no repairs)."""
    result = sphere_nlp.parameterize(meshgen.ellipsoid(1), target="original-angles")
    assert result.repairs == [] and result.certificate.valid
    np.testing.assert_array_equal(result.vertex_map, np.arange(len(result.vertices)))
    return result


def test_soup_is_welded_solved_and_mapped(ellipsoid_result):
    V, F = meshgen.ellipsoid(1)
    soup_V, soup_F = meshgen.soup(V, F)
    result = sphere_nlp.parameterize((soup_V, soup_F), target="original-angles")
    assert result.certificate.valid
    assert len(result.vertices) == len(V) and len(result.vertex_map) == len(soup_V)
    assert result.repairs == ["merged %d duplicate vertex(es) into %d (coincident within 1e-12 of the "
                              "bounding-box diagonal)" % (len(soup_V) - len(V), len(V))]
    # Soup vertex k is a copy of original vertex F.flat[k]: all copies land on one sphere point ...
    original_of_soup = F.ravel()
    sphere_of_original = np.zeros((len(V), 3))
    sphere_of_original[original_of_soup] = result.vertices[result.vertex_map]
    np.testing.assert_array_equal(result.vertices[result.vertex_map], sphere_of_original[original_of_soup])
    # ... the repaired vertices keep the soup's order (first copy of each), with their input positions ...
    first_copy = np.unique(result.vertex_map, return_index=True)[1]
    assert np.all(np.diff(first_copy) > 0)
    np.testing.assert_array_equal(result.input_vertices, soup_V[first_copy])
    # ... and the solve is the same as on the welded mesh (same faces, same corner order).
    np.testing.assert_allclose(result.angles, ellipsoid_result.angles, atol=1e-7)


def test_near_duplicates_are_welded_relative_to_the_bounding_box():
    V, F = icosphere(1)
    V = V * 1e3 + 5e3
    soup_V, soup_F = meshgen.soup(V, F)
    rng = np.random.default_rng(1)
    # 1e-13 of the diagonal: below the 1e-12 weld tolerance, far above the coordinates' rounding.
    nudged = soup_V + rng.uniform(-1, 1, soup_V.shape) * 1e-13 * 2e3 / np.sqrt(3)
    mesh = prepare_mesh(nudged, soup_F)
    assert len(mesh.vertices) == len(V)
    # A gap of 1e-9 of the diagonal is not a duplicate: the soup stays open.
    apart = soup_V + rng.uniform(-1, 1, soup_V.shape) * 1e-9 * 2e3
    with pytest.raises(sphere_nlp.OpenBoundaryError):
        prepare_mesh(apart, soup_F)


def test_valid_mesh_with_touching_vertices_is_not_welded():
    # Two vertices with no face in common placed at the same point: the surface touches itself, but it
    # is a valid closed surface as given, so merging them (which would pinch it) must not happen.
    V, F = icosphere(1)
    far = int(np.argmin(V @ V[0]))
    V[far] = V[0]
    result = sphere_nlp.parameterize((V, F), target="equal-angles")
    assert result.certificate.valid and result.repairs == [] and len(result.vertices) == len(V)


def test_unreferenced_vertices_are_dropped_keeping_input_order(tmp_path, capsys):
    V, F = meshgen.ellipsoid(1)
    # Insert stray vertices at the front and in the middle (one far away, one a duplicate).
    stray = np.array([[100.0, 100, 100], V[5]])
    V2 = np.vstack([stray[:1], V[:20], stray[1:], V[20:]])
    F2 = np.where(F < 20, F + 1, F + 2)
    result = sphere_nlp.parameterize((V2, F2), target="equal-angles")
    assert result.certificate.valid
    assert result.repairs == ["dropped 2 unreferenced vertex(es) (e.g. vertex 0)"]
    assert result.vertex_map[0] == -1 and result.vertex_map[21] == -1
    np.testing.assert_array_equal(result.vertex_map[result.vertex_map >= 0], np.arange(len(V)))
    np.testing.assert_array_equal(result.input_vertices, V)
    np.testing.assert_array_equal(result.faces, F)

    source, out = tmp_path / "stray.off", tmp_path / "sphere.off"
    write_mesh(source, V2, F2)
    assert main([str(source), "-o", str(out), "--target", "equal-angles"]) == 0
    assert "repaired: dropped 2 unreferenced vertex(es) (e.g. vertex 0)" in capsys.readouterr().err
    X, F_out = load_mesh(out)
    assert len(X) == len(V) and certify(X, F_out).valid
    np.testing.assert_array_equal(F_out, F)


def test_globally_inward_orientation_needs_no_repair(ellipsoid_result):
    # The method is intrinsic (angles only), so a mesh wound inward maps as well as one wound outward:
    # the sphere's faces keep the input's winding and are counter-clockwise seen from outside.
    V, F = meshgen.ellipsoid(1)
    result = sphere_nlp.parameterize((V, F[:, ::-1]), target="original-angles")
    assert result.certificate.valid and result.repairs == []
    np.testing.assert_array_equal(result.faces, F[:, ::-1])
    np.testing.assert_allclose(result.angles, ellipsoid_result.angles[:, ::-1], atol=1e-7)


def test_partly_inconsistent_orientation_is_repaired(ellipsoid_result):
    V, F = meshgen.ellipsoid(1)
    F2 = F.copy()
    F2[[3, 10, 11]] = F2[[3, 10, 11], ::-1]
    result = sphere_nlp.parameterize((V, F2), target="original-angles")
    assert result.certificate.valid
    assert result.repairs == ["flipped 3 face(s) to make the orientation consistent"]
    np.testing.assert_array_equal(result.faces, F)
    np.testing.assert_allclose(result.angles, ellipsoid_result.angles, atol=1e-7)


@pytest.mark.parametrize("scale, offset", [(1e-150, 0.0), (1e150, 0.0), (1.0, 1e9), (1e-9, -1e-5)])
def test_extreme_scales_and_offsets_are_normalised(scale, offset, ellipsoid_result):
    V, F = meshgen.ellipsoid(1)
    result = sphere_nlp.parameterize((V * scale + offset, F), target="original-angles")
    assert result.certificate.valid
    assert len(result.repairs) == 1 and result.repairs[0].startswith("normalised coordinates")
    np.testing.assert_array_equal(result.input_vertices, V * scale + offset)   # not the normalised copy
    # Scales cost nothing; an offset costs the input its low bits (1e9 + x keeps ~7 digits of x),
    # which no normalisation can bring back.
    tolerance = 1e-7 + 1e2 * np.finfo(float).eps * abs(offset) / scale
    np.testing.assert_allclose(result.target_angles, ellipsoid_result.target_angles, atol=tolerance)
    np.testing.assert_allclose(result.angles, ellipsoid_result.angles, atol=tolerance)


@pytest.mark.parametrize("target", ["original-angles", "equal-angles"])
def test_sliver_of_006_degrees_is_accepted(target):
    # A 0.06 degree sliver is thin but not degenerate (the limit is 1e-10 rad): it must be solved.
    height = np.tan(np.radians(0.06)) * np.sqrt(0.5)
    V, F = meshgen.flattened_octahedron(height)
    result = sphere_nlp.parameterize((V, F), target=target)
    assert result.certificate.valid
    assert np.degrees(result.target_angles.min()) == pytest.approx(0.06) or target == "equal-angles"


def test_stl_soup_file_is_welded_from_the_cli(tmp_path, capsys):
    import trimesh

    V, F = meshgen.ellipsoid(1)
    source = tmp_path / "ellipsoid.stl"
    source.write_bytes(trimesh.Trimesh(V, F, process=False).export(file_type="stl"))
    out = tmp_path / "sphere.ply"
    assert main([str(source), "-o", str(out), "--save-solution", str(tmp_path / "s.npz")]) == 0
    stderr = capsys.readouterr().err
    assert "repaired: merged %d duplicate vertex(es) into %d" % (3 * len(F) - len(V), len(V)) in stderr
    X, F_out = load_mesh(out)
    assert len(X) == len(V) and certify(X, F_out).valid
    vertex_map = np.load(tmp_path / "s.npz")["vertex_map"]
    np.testing.assert_array_equal(F_out.ravel(), vertex_map)     # STL vertex k is corner k
