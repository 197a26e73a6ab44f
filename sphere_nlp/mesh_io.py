"""Reading meshes (anything trimesh reads) and writing results atomically.

Every writer goes to a temporary file in the destination folder and renames it into place, so a
failure or Ctrl-C never leaves a partial file, and an existing file is replaced only by a finished one.
"""

import json
import os
import tempfile
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from . import errors

MESH_FORMATS = (".off", ".obj", ".ply")


def load_mesh(path):
    """Read a triangle mesh file, returning ``(vertices (n, 3) float, faces (t, 3) int)``.

    Vertices and faces are returned exactly as stored (no merging, no reordering).

    Raises
    ------
    UnreadableMeshError
        Missing, empty or unparsable file, or no triangles in it.
    """
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise errors.UnreadableMeshError("cannot read %s: no such file" % path)
    if path.stat().st_size == 0:
        raise errors.UnreadableMeshError("cannot read %s: the file is empty" % path)
    try:
        loaded = trimesh.load(str(path), process=False, force="mesh")
        vertices = np.asarray(loaded.vertices, dtype=float)
        faces = np.asarray(loaded.faces, dtype=np.int64)
    except Exception as exc:  # trimesh raises many types for bad files
        detail = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise errors.UnreadableMeshError("cannot read %s as a mesh: %s" % (path, detail)) from None
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0 or len(vertices) == 0:
        raise errors.UnreadableMeshError("cannot read %s as a mesh: it contains no triangles" % path)
    return vertices, faces


@contextmanager
def atomic_output(path, mode="w"):
    """Open a temporary file beside ``path``; rename it to ``path`` only if the block succeeds."""
    path = Path(path)
    directory = path.parent if str(path.parent) else Path(".")
    fd, tmp = tempfile.mkstemp(prefix="." + path.name + ".", suffix=".tmp", dir=directory)
    # mkstemp makes the file private (0600); give it the permissions a plain open() would.
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)
    try:
        with os.fdopen(fd, mode) as handle:
            yield handle
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def check_mesh_path(path):
    """Raise UsageError unless ``path`` has a mesh extension we can write."""
    if Path(path).suffix.lower() not in MESH_FORMATS:
        raise errors.UsageError("cannot write %s: output must end in %s" % (path, ", ".join(MESH_FORMATS)))


def write_mesh(path, vertices, faces):
    """Write a triangle mesh as OFF, OBJ or PLY (ASCII), chosen by the extension.

    Coordinates are written with 17 significant digits, so they read back bit for bit and the
    certificate computed before writing holds for the file.
    """
    check_mesh_path(path)
    suffix = Path(path).suffix.lower()
    vertices = np.asarray(vertices, float)
    faces = np.asarray(faces, np.int64)
    vertex_lines = "\n".join("%.17g %.17g %.17g" % tuple(v) for v in vertices)
    with atomic_output(path) as out:
        if suffix == ".off":
            out.write("OFF\n%d %d 0\n" % (len(vertices), len(faces)))
            out.write(vertex_lines + "\n")
            out.write("\n".join("3 %d %d %d" % tuple(f) for f in faces) + "\n")
        elif suffix == ".obj":
            out.write("# written by sphere_nlp\n")
            out.write("".join("v " + line + "\n" for line in vertex_lines.split("\n")))
            out.write("\n".join("f %d %d %d" % tuple(f + 1) for f in faces) + "\n")
        else:
            out.write("ply\nformat ascii 1.0\ncomment written by sphere_nlp\n"
                      "element vertex %d\nproperty double x\nproperty double y\nproperty double z\n"
                      "element face %d\nproperty list uchar int vertex_indices\nend_header\n"
                      % (len(vertices), len(faces)))
            out.write(vertex_lines + "\n")
            out.write("\n".join("3 %d %d %d" % tuple(f) for f in faces) + "\n")


def write_json(path, data):
    """Write a JSON document atomically."""
    with atomic_output(path) as out:
        json.dump(data, out, indent=2)
        out.write("\n")


def write_npz(path, **arrays):
    """Write a .npz archive atomically."""
    with atomic_output(path, "wb") as out:
        np.savez(out, **arrays)
