"""Bad input: every defect is one line on stderr and exit status 2 (CLI), or its own exception (API).

Each case is a small mesh built by code (tests/meshgen.py) or a few bytes of file text. Every CLI case
also checks that nothing was written: no output file and no temporary file.
"""

import numpy as np
import pytest

import sphere_nlp
from sphere_nlp import errors
from sphere_nlp.cli import main
from sphere_nlp.mesh_io import write_mesh
from sphere_nlp.shapes import octahedron, tetrahedron

import meshgen


def _with(builder, edit):
    """A builder that applies ``edit(V, F)`` to a copy of another builder's mesh."""
    def build():
        V, F = builder()
        V, F = V.copy(), F.copy()
        edit(V, F)
        return V, F
    return build


def _set(array_name, index, value):
    def edit(V, F):
        (V if array_name == "V" else F)[index] = value
    return edit


# id: (mesh builder, exception class, fragments the message must contain)
ARRAY_DEFECTS = {
    "face-index-too-large": (_with(octahedron, _set("F", (3, 1), 17)), errors.FaceIndexError,
                             ["face 3 refers to vertex 17", "6 vertices"]),
    "face-index-negative": (_with(octahedron, _set("F", (5, 0), -1)), errors.FaceIndexError,
                            ["face 5 refers to vertex -1"]),
    "face-repeats-vertex": (_with(octahedron, _set("F", 2, [1, 1, 4])), errors.FaceIndexError,
                            ["repeat a vertex index", "face 2"]),
    "nan-coordinate": (_with(octahedron, _set("V", (2, 1), np.nan)), errors.NonFiniteCoordinatesError,
                       ["1 vertex(es) have non-finite", "vertex 2"]),
    "inf-coordinate": (_with(octahedron, _set("V", (4, 0), -np.inf)), errors.NonFiniteCoordinatesError,
                       ["vertex 4"]),
    "open-boundary": (meshgen.open_cylinder, errors.OpenBoundaryError,
                      ["3 boundary edge(s)", "e.g. 72-83", "must be closed"]),
    "open-soup": (lambda: meshgen.soup(*meshgen.open_cylinder()), errors.OpenBoundaryError,
                  ["3 boundary edge(s)"]),
    "non-manifold-edge": (meshgen.finned_octahedron, errors.NonManifoldEdgeError,
                          ["1 non-manifold edge(s)", "e.g. 0-2"]),
    "pinched-vertex": (meshgen.pinched_sphere, errors.NonManifoldVertexError,
                       ["1 non-manifold (pinched) vertex(es)", "vertex 0"]),
    "touching-tetrahedra": (lambda: meshgen.two_tetrahedra(shared_vertex=True),
                            errors.NonManifoldVertexError, ["pinched", "vertex 0"]),
    "two-components": (meshgen.two_tetrahedra, errors.ComponentsError,
                       ["2 connected components", "4, 4"]),
    "genus-1": (meshgen.torus, errors.GenusError, ["genus 1"]),
    "non-orientable": (meshgen.projective_plane, errors.OrientationError, ["not orientable"]),
    "zero-area-face": (lambda: meshgen.flattened_octahedron(0.0), errors.DegenerateFaceError,
                       ["1 degenerate (zero-area) face(s)", "face 0"]),
    "near-zero-area-face": (lambda: meshgen.flattened_octahedron(1e-12), errors.DegenerateFaceError,
                            ["face 0", "smallest angle 1.41e-12 rad"]),
    "all-vertices-coincide": (lambda: (np.zeros((4, 3)), tetrahedron()[1]), errors.DegenerateFaceError,
                              ["same point"]),
}


@pytest.mark.parametrize("case", ARRAY_DEFECTS, ids=list(ARRAY_DEFECTS))
def test_api_raises_one_exception_type_per_defect(case):
    builder, error, fragments = ARRAY_DEFECTS[case]
    with pytest.raises(error) as info:
        sphere_nlp.parameterize(builder())
    message = str(info.value)
    assert "\n" not in message
    for fragment in fragments:
        assert fragment in message
    assert info.value.exit_status == 2 and isinstance(info.value, errors.MeshInputError)


def run_cli(capsys, *args):
    """Run the CLI in this process (fast); return (exit status, stderr)."""
    status = main([str(a) for a in args])
    return status, capsys.readouterr().err


def assert_one_error_line(stderr, fragments):
    lines = stderr.strip().splitlines()
    assert len(lines) == 1, stderr
    assert lines[0].startswith("sphere-nlp: error: ") and "Traceback" not in stderr
    for fragment in fragments:
        assert fragment in lines[0], lines[0]


@pytest.mark.parametrize("case", ARRAY_DEFECTS, ids=list(ARRAY_DEFECTS))
def test_cli_rejects_defect_with_exit_2_and_writes_nothing(case, tmp_path, capsys):
    builder, _, fragments = ARRAY_DEFECTS[case]
    source = tmp_path / "in" / "mesh.off"
    source.parent.mkdir()
    write_mesh(source, *builder())
    out = tmp_path / "out"
    out.mkdir()
    status, stderr = run_cli(capsys, source, "-o", out / "sphere.off", "--quiet")
    assert status == 2
    assert_one_error_line(stderr, fragments)
    assert list(out.iterdir()) == []


TETRA_OFF = ("OFF\n4 4 0\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n"
             "3 0 2 1\n3 0 1 3\n3 0 3 2\n3 1 2 3\n")

# id: (file name, file content (None: do not create), exception class, fragments)
FILE_DEFECTS = {
    "missing": ("mesh.off", None, errors.UnreadableMeshError, ["no such file"]),
    "empty": ("mesh.off", "", errors.UnreadableMeshError, ["the file is empty"]),
    "blank-lines": ("mesh.off", "\n \n\n", errors.UnreadableMeshError, ["not an OFF file"]),
    "garbage-text": ("mesh.off", "hello world\nthis is no mesh\n", errors.UnreadableMeshError,
                     ["not an OFF file"]),
    "binary-garbage": ("mesh.off", bytes(range(256)) * 4, errors.UnreadableMeshError, ["binary data"]),
    "truncated-faces": ("mesh.off", TETRA_OFF.rsplit("3 0 1 3", 1)[0], errors.UnreadableMeshError,
                        ["truncated", "promises 4 vertices and 4 faces, found 4 and 1"]),
    "truncated-vertices": ("mesh.off", "OFF\n4 4 0\n0 0 0\n1 0 0\n", errors.UnreadableMeshError,
                           ["truncated", "found 2 and 0"]),
    "bad-counts": ("mesh.off", "OFF\nfour 4 0\n", errors.UnreadableMeshError, ["not two integers"]),
    "zero-counts": ("mesh.off", "OFF\n0 0 0\n", errors.UnreadableMeshError, ["declares 0 vertices"]),
    "word-for-coordinate": ("mesh.off", TETRA_OFF.replace("0 1 0", "0 one 0"), errors.UnreadableMeshError,
                            ["line 5", "not a number"]),
    "short-vertex": ("mesh.off", TETRA_OFF.replace("0 1 0", "0 1"), errors.UnreadableMeshError,
                     ["line 5", "vertex 2 has 2 coordinate(s)"]),
    # Polygons are split into triangles (tests/test_formats.py); what is left is the real defect.
    "off-quad": ("mesh.off", "OFF\n5 2 0\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n0 0 1\n4 0 1 2 3\n3 0 1 4\n",
                 errors.OpenBoundaryError, ["boundary edge"]),
    "off-two-corner-face": ("mesh.off", TETRA_OFF.replace("3 0 1 3", "2 0 1"), errors.UnreadableMeshError,
                            ["face 1 has 2 corner(s): a face needs at least 3"]),
    "off-index-out-of-range": ("mesh.off", TETRA_OFF.replace("3 1 2 3", "3 1 2 9"), errors.FaceIndexError,
                               ["face 3 refers to vertex 9"]),
    "obj-quad": ("mesh.obj", "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3 4\n", errors.OpenBoundaryError,
                 ["boundary edge"]),
    "obj-two-corner-face": ("mesh.obj", "v 0 0 0\nv 1 0 0\nv 1 1 0\nf 1 2 3\nf 1 2\n", errors.UnreadableMeshError,
                            ["face 1 has 2 corner(s)"]),
    "obj-index-out-of-range": ("mesh.obj", "v 0 0 0\nv 1 0 0\nv 1 1 0\nf 1 2 3\nf 1 3 7\n",
                               errors.FaceIndexError,
                               ["line 5", "face 1 refers to a vertex that does not exist"]),
    "obj-no-faces": ("mesh.obj", "v 0 0 0\nv 1 0 0\n", errors.UnreadableMeshError, ["no triangles"]),
    "obj-garbage": ("mesh.obj", "<html>not found</html>\n", errors.UnreadableMeshError, ["not an OBJ file"]),
    "ply-truncated": ("mesh.ply", "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\n"
                                  "property float y\nproperty float z\nelement face 4\n"
                                  "property list uchar int vertex_indices\nend_header\n"
                                  "0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 2 1\n3 0 1 3\n",
                      errors.UnreadableMeshError, ["truncated", "promises 4 faces, found 2"]),
    "ply-quad": ("mesh.ply", "ply\nformat ascii 1.0\nelement vertex 5\nproperty float x\n"
                             "property float y\nproperty float z\nelement face 2\n"
                             "property list uchar int vertex_indices\nend_header\n"
                             "0 0 0\n1 0 0\n1 1 0\n0 1 0\n0 0 1\n4 0 1 2 3\n3 0 1 4\n",
                 errors.OpenBoundaryError, ["boundary edge"]),
    "ply-garbage": ("mesh.ply", "ply\nthis is not really a ply file\n", errors.UnreadableMeshError,
                    ["cannot read"]),
    "stl-truncated": ("mesh.stl", "solid x\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\n",
                      errors.UnreadableMeshError, ["cannot read"]),
}


def _write_case(directory, name, content):
    path = directory / name
    if isinstance(content, bytes):
        path.write_bytes(content)
    elif content is not None:
        path.write_text(content)
    return path


@pytest.mark.parametrize("case", FILE_DEFECTS, ids=list(FILE_DEFECTS))
def test_api_rejects_bad_file(case, tmp_path):
    name, content, error, fragments = FILE_DEFECTS[case]
    path = _write_case(tmp_path, name, content)
    with pytest.raises(error) as info:
        sphere_nlp.parameterize(path)
    assert "\n" not in str(info.value)
    for fragment in fragments:
        assert fragment in str(info.value)


@pytest.mark.parametrize("case", FILE_DEFECTS, ids=list(FILE_DEFECTS))
def test_cli_rejects_bad_file_with_exit_2(case, tmp_path, capsys):
    name, content, _, fragments = FILE_DEFECTS[case]
    (tmp_path / "in").mkdir()
    path = _write_case(tmp_path / "in", name, content)
    out = tmp_path / "out"
    out.mkdir()
    status, stderr = run_cli(capsys, path, "-o", out / "sphere.obj", "-q")
    assert status == 2
    assert_one_error_line(stderr, fragments)
    assert list(out.iterdir()) == []


def test_cli_without_quiet_still_ends_in_one_error_line(tmp_path, capsys):
    path = tmp_path / "mesh.off"
    write_mesh(path, *meshgen.torus())
    status, stderr = run_cli(capsys, path, "-o", tmp_path / "s.off")
    assert status == 2
    # Progress is announced only once the mesh is valid, so the error is the only line.
    assert stderr.strip().splitlines() == ["sphere-nlp: error: mesh has genus 1 (V - E + F = 0): only "
                                           "genus 0 (sphere-like) surfaces can be mapped to the sphere"]
    assert "Traceback" not in stderr and not (tmp_path / "s.off").exists()
    status, stderr = run_cli(capsys, tmp_path / "missing.off", "-o", tmp_path / "s.off")
    assert status == 2
    assert_one_error_line(stderr, ["missing.off"])


def test_cli_debug_shows_a_traceback(tmp_path, capsys):
    status, stderr = run_cli(capsys, tmp_path / "nope.off", "-o", tmp_path / "s.off", "--debug")
    assert status == 2 and "Traceback" in stderr and "no such file" in stderr


def test_api_rejects_bad_arrays():
    V, F = octahedron()
    with pytest.raises(errors.FaceIndexError, match="integers"):
        sphere_nlp.parameterize((V, F + 0.5))
    with pytest.raises(errors.FaceIndexError, match="non-empty"):
        sphere_nlp.parameterize((V, F[:, :2]))
    with pytest.raises(errors.UnreadableMeshError, match=r"\(n, 3\)"):
        sphere_nlp.parameterize((V[:, :2], F))
    with pytest.raises(errors.FaceIndexError, match="ragged"):
        sphere_nlp.parameterize((V, [[0, 1, 2], [0, 1, 2, 3]]))
    with pytest.raises(errors.UnreadableMeshError, match="numbers"):
        sphere_nlp.parameterize(([["a", "b", "c"]], F))
    with pytest.raises(errors.UsageError):
        sphere_nlp.parameterize(42)
    with pytest.raises(errors.UsageError, match="unknown target"):
        sphere_nlp.parameterize((V, F), target="nonsense")


def test_every_exception_is_exported_and_categorised():
    for name in sphere_nlp.__all__:
        obj = getattr(sphere_nlp, name)
        if isinstance(obj, type) and issubclass(obj, Exception):
            assert issubclass(obj, errors.SphereNLPError)
            expected = 2 if issubclass(obj, errors.MeshInputError) else 1
            assert obj.exit_status == expected, name
