"""Formats beyond OFF/OBJ/PLY: FreeSurfer and GIFTI surfaces in, polygons split, glTF out, and the
per-face / per-vertex distortion file."""

import numpy as np
import pytest

import sphere_nlp
from sphere_nlp.certify import certify
from sphere_nlp.cli import main
from sphere_nlp.mesh_io import load_mesh, read_mesh, write_mesh

from conftest import MODELS, shared_mesh


@pytest.fixture(scope="module")
def bunny_as_float32(tmp_path_factory):
    """bunny.off's vertices rounded to 32-bit floats (what FreeSurfer and GIFTI files hold), as an
    OFF, and the sphere the main command writes for it."""
    V, F = load_mesh(shared_mesh("bunny.off"))
    V = V.astype(np.float32).astype(float)
    folder = tmp_path_factory.mktemp("bunny")
    write_mesh(folder / "bunny32.off", V, F)
    assert main([str(folder / "bunny32.off"), "-o", str(folder / "bunny32.sphere.off"), "-q"]) == 0
    return folder, V, F, load_mesh(folder / "bunny32.sphere.off")[0]


def _write_freesurfer(path, V, F):
    nibabel = pytest.importorskip("nibabel")
    nibabel.freesurfer.write_geometry(str(path), V, F)


def _write_gifti(path, V, F):
    nibabel = pytest.importorskip("nibabel")
    image = nibabel.gifti.GiftiImage(darrays=[
        nibabel.gifti.GiftiDataArray(V.astype(np.float32), intent="NIFTI_INTENT_POINTSET"),
        nibabel.gifti.GiftiDataArray(F.astype(np.int32), intent="NIFTI_INTENT_TRIANGLE")])
    nibabel.save(image, str(path))


@pytest.mark.parametrize("name, writer", [("lh.pial", _write_freesurfer), ("bunny.surf.gii", _write_gifti)])
def test_neuroimaging_surfaces_map_to_the_sphere_of_the_same_mesh(bunny_as_float32, name, writer):
    folder, V, F, sphere = bunny_as_float32
    writer(folder / name, V, F)
    read_V, read_F, notes = read_mesh(folder / name)
    assert np.array_equal(read_V, V) and np.array_equal(read_F, F) and notes == []
    out = folder / (name + ".sphere.off")
    assert main([str(folder / name), "-o", str(out), "-q"]) == 0
    S, G = load_mesh(out)
    # The same vertices and triangles give the same map, bit for bit, certified.
    assert np.array_equal(G, F) and np.array_equal(S, sphere) and certify(S, G).valid


def test_a_truncated_or_quadrangle_freesurfer_file_is_one_error_line(tmp_path, capsys):
    from sphere_nlp.shapes import icosphere

    _write_freesurfer(tmp_path / "lh.white", *icosphere(2))
    data = (tmp_path / "lh.white").read_bytes()
    (tmp_path / "lh.cut").write_bytes(data[:len(data) // 2])
    (tmp_path / "lh.quad").write_bytes(b"\xff\xff\xff" + data[3:])
    for name, words in (("lh.cut", "truncated (header promises 162 vertices and 320 faces"),
                        ("lh.quad", "FreeSurfer quadrangle surface")):
        assert main([str(tmp_path / name), "-o", str(tmp_path / "s.off")]) == 2
        [line] = capsys.readouterr().err.strip().splitlines()
        assert line.startswith("sphere-nlp: error: cannot read") and words in line
    assert not (tmp_path / "s.off").exists()


def uv_sphere_polygons(n_lon=8, n_lat=6):
    """A closed sphere of quadrangles between latitude rings and triangles at the poles (OBJ text,
    1-based), and its numbers of vertices, quadrangles and triangles."""
    lat = np.pi * np.arange(1, n_lat) / n_lat
    lon = 2 * np.pi * np.arange(n_lon) / n_lon
    rings = [[np.sin(a) * np.cos(b), np.sin(a) * np.sin(b), np.cos(a)] for a in lat for b in lon]
    V = np.array([[0, 0, 1.0]] + rings + [[0, 0, -1.0]])
    ring = lambda r, k: 2 + r * n_lon + k % n_lon                      # noqa: E731 (1-based)
    faces = [[1, ring(0, k), ring(0, k + 1)] for k in range(n_lon)]
    faces += [[ring(r, k), ring(r + 1, k), ring(r + 1, k + 1), ring(r, k + 1)]
              for r in range(n_lat - 2) for k in range(n_lon)]
    faces += [[len(V), ring(n_lat - 2, k + 1), ring(n_lat - 2, k)] for k in range(n_lon)]
    text = "".join("v %.17g %.17g %.17g\n" % tuple(v) for v in V) + "".join("f " + " ".join(map(str, f)) + "\n"
                                                                      for f in faces)
    return text, len(V), n_lon * (n_lat - 2), 2 * n_lon


@pytest.mark.parametrize("suffix", [".obj", ".off"])
def test_polygons_are_split_into_triangles_and_the_run_says_so(tmp_path, capsys, suffix):
    text, n, quads, triangles = uv_sphere_polygons()
    if suffix == ".off":
        lines = text.splitlines()
        vs = [line[2:] for line in lines if line.startswith("v ")]
        fs = [[int(i) - 1 for i in line.split()[1:]] for line in lines if line.startswith("f ")]
        text = "OFF\n%d %d 0\n" % (len(vs), len(fs)) + "\n".join(vs) + "\n" + "".join(
            "%d %s\n" % (len(f), " ".join(map(str, f))) for f in fs)
    (tmp_path / ("m" + suffix)).write_text(text)
    assert main([str(tmp_path / ("m" + suffix)), "-o", str(tmp_path / "s.off")]) == 0
    [line] = [x for x in capsys.readouterr().err.splitlines() if x.startswith("repaired: split")]
    assert line == ("repaired: split %d face(s) of more than 3 corners into triangles (%d faces became %d "
                    "triangles; the split sets their target angles)" % (quads, quads + triangles, 2 * quads + triangles))
    S, F = load_mesh(tmp_path / "s.off")
    V, G, _ = read_mesh(tmp_path / ("m" + suffix))
    # The sphere has the input's vertices one for one and the triangles the split made.
    assert len(S) == n and np.array_equal(F, G) and len(F) == 2 * quads + triangles and certify(S, F).valid


@pytest.mark.parametrize("suffix", [".glb", ".gltf"])
def test_gltf_output_holds_the_certified_sphere_in_32_bit_floats(tmp_path, suffix):
    result = sphere_nlp.parameterize(str(MODELS / "cylinder.off"))
    result.write(tmp_path / ("s" + suffix))
    S, F = load_mesh(tmp_path / ("s" + suffix))
    assert np.array_equal(F, result.faces)
    assert np.array_equal(S, np.asarray(result.vertices, np.float32).astype(float))
    assert certify(S / np.linalg.norm(S, axis=1, keepdims=True), F).valid
    assert main([str(MODELS / "cylinder.off"), "-o", str(tmp_path / ("cli" + suffix)), "-q"]) == 0
    assert np.array_equal(load_mesh(tmp_path / ("cli" + suffix))[1], F)


def test_distortion_file_holds_per_face_and_per_vertex_distortion(tmp_path):
    from sphere_nlp.geometry import corner_angles
    import json

    out = tmp_path / "d.npz"
    assert main([str(MODELS / "cylinder.off"), "-o", str(tmp_path / "s.off"), "--save-distortion", str(out),
                 "--report", str(tmp_path / "r.json"), "-q"]) == 0
    d = np.load(out)
    X, F = load_mesh(MODELS / "cylinder.off")
    S, _ = load_mesh(tmp_path / "s.off")
    assert np.array_equal(d["faces"], F) and d["face_log_area_ratio"].shape == (len(F),)
    # The corner values are the angle changes measured here from the files; the means are the report's.
    corners = np.degrees(np.abs(corner_angles(S, F) - corner_angles(X, F)))
    assert np.allclose(d["corner_angle_distortion_deg"], corners, atol=1e-9)
    report = json.loads((tmp_path / "r.json").read_text())["distortion"]
    assert np.mean(np.abs(d["face_log_area_ratio"])) == pytest.approx(report["mean_abs_log_area"], rel=1e-12)
    assert d["corner_angle_distortion_deg"].mean() == pytest.approx(report["mean_abs_angle_diff_deg"], rel=1e-12)
    # Each vertex has the mean of the faces around it.
    k = 5
    around = (F == k).any(axis=1)
    assert d["vertex_log_area_ratio"][k] == pytest.approx(d["face_log_area_ratio"][around].mean(), rel=1e-12)
    assert d["vertex_angle_distortion_deg"].shape == (len(S),)
