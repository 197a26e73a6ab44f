"""The OFF and OBJ readers: the whole-buffer readers give exactly what the line-by-line readers give
(arrays, or the same error), and a large file of vertices alone is refused quickly in little memory."""

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from sphere_nlp import errors, mesh_io

from conftest import SHARED_MESHES

TETRA_V = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\n"
TETRA_F = "f 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"
TETRA_OFF = "OFF\n4 4 0\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 2 1\n3 0 1 3\n3 0 3 2\n3 1 2 3\n"

# id: (file name, content); True in the third place: the whole-buffer reader must take it.
CASES = {
    "obj-plain": ("m.obj", TETRA_V + TETRA_F, True),
    "obj-texture-normal": ("m.obj", TETRA_V + "vt 0 0\nvt 1 0\nvn 0 0 1\n"
                           "f 1/1/1 3/2/1 2/1/1\nf 1//1 2//1 4//1\nf 1/2 4/1 3/2\nf 2 3 4\n", True),
    "obj-comments-groups": ("m.obj", "# made by hand\nmtllib a.mtl\no tetra\n" + TETRA_V.replace("\n", " # v\n", 1)
                            + "g side\nusemtl red\ns off\n\n   " + TETRA_F.replace("\n", "\n\t", 2), True),
    "obj-negative": ("m.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf -3 -1 -2\nv 0 0 1\nf 1 2 -1\nf -4 -1 3\n"
                     "f 2 3 4\n", True),
    "obj-extra-columns": ("m.obj", TETRA_V.replace("\n", " 1 0.5 0.25\n") + TETRA_F, True),
    "obj-numbers": ("m.obj", "v 1e-3 +.5 -0\nv 5. -2E+2 0.1\nv 3 0 1\nv 0 7 1e300\n" + TETRA_F, True),
    "obj-crlf": ("m.obj", (TETRA_V + TETRA_F).replace("\n", "\r\n"), True),
    "obj-cr": ("m.obj", (TETRA_V + TETRA_F).replace("\n", "\r"), True),
    "obj-bom": ("m.obj", b"\xef\xbb\xbf" + (TETRA_V + TETRA_F).encode(), True),
    "obj-no-final-newline": ("m.obj", (TETRA_V + TETRA_F).rstrip("\n"), True),
    "obj-utf16": ("m.obj", (TETRA_V + TETRA_F).encode("utf-16"), False),
    "obj-underscore": ("m.obj", TETRA_V.replace("v 1 0 0", "v 1_0 0 0") + TETRA_F, False),
    "obj-quad": ("m.obj", TETRA_V + "f 1 2 3 4\n" + TETRA_F, False),
    "obj-two-corners": ("m.obj", TETRA_V + "f 1 2\n" + TETRA_F, False),
    "obj-index-zero": ("m.obj", TETRA_V + "f 0 1 2\n" + TETRA_F, False),
    "obj-index-too-large": ("m.obj", TETRA_V + TETRA_F + "f 1 2 9\n", False),
    "obj-index-beyond-64-bits": ("m.obj", TETRA_V + TETRA_F + "f 1 2 99999999999999999999\n", False),
    "obj-word-coordinate": ("m.obj", TETRA_V.replace("v 0 1 0", "v 0 one 0") + TETRA_F, False),
    "obj-short-vertex": ("m.obj", TETRA_V.replace("v 0 1 0", "v 0 1") + TETRA_F, False),
    "obj-glued-numbers": ("m.obj", TETRA_V.replace("v 0 1 0", "v 0 1-2 0") + TETRA_F, False),
    "obj-no-faces": ("m.obj", TETRA_V, False),
    "off-plain": ("m.off", TETRA_OFF, True),
    "off-counts-on-header": ("m.off", TETRA_OFF.replace("OFF\n", "OFF "), True),
    "off-comments-blank-lines": ("m.off", "# tetra\n" + TETRA_OFF.replace("0 0 1\n", "0 0 1 # last\n\n  \n"),
                                 True),
    "off-extra-columns": ("m.off", "C" + TETRA_OFF.replace("0 1 0\n", "0 1 0 255 0 0 255\n"), True),
    "off-crlf": ("m.off", TETRA_OFF.replace("\n", "\r\n"), True),
    "off-face-colours": ("m.off", TETRA_OFF.replace("3 0 2 1\n", "3 0 2 1 0.5 0.5 0.5\n"), False),
    "off-quad": ("m.off", "OFF\n5 2 0\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n0 0 1\n4 0 1 2 3\n3 0 1 4\n", False),
    "off-index-beyond-64-bits": ("m.off", TETRA_OFF.replace("3 1 2 3", "3 1 2 99999999999999999999"), False),
    "off-truncated": ("m.off", TETRA_OFF.rsplit("3 0 1 3", 1)[0], False),
    "off-word-coordinate": ("m.off", TETRA_OFF.replace("0 1 0", "0 one 0"), False),
}


def _outcome(path):
    """What load_mesh makes of a file: its arrays, or its error's type and message."""
    try:
        return mesh_io.load_mesh(path)
    except errors.SphereNLPError as exc:
        return type(exc), str(exc)


def _line_by_line(monkeypatch):
    monkeypatch.setattr(mesh_io, "_read_obj_whole", lambda path: None)
    monkeypatch.setattr(mesh_io, "_read_off_body_whole", lambda *args: None)


def _same(a, b):
    if isinstance(a[0], type) or isinstance(b[0], type):
        return a == b
    # Bit for bit, the sign of zero included.
    return all(x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes() for x, y in zip(a, b))


@pytest.mark.parametrize("case", CASES, ids=list(CASES))
def test_whole_buffer_reader_agrees_with_line_by_line_reader(case, tmp_path, monkeypatch):
    name, content, whole_takes_it = CASES[case]
    path = tmp_path / name
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        path.write_bytes(content.encode())
    taken = []
    for reader in ("_read_obj_whole", "_read_off_body_whole"):
        original = getattr(mesh_io, reader)
        monkeypatch.setattr(mesh_io, reader,
                            lambda *args, original=original: taken.append(original(*args)) or taken[-1])
    fast = _outcome(path)
    assert any(result is not None for result in taken) == whole_takes_it
    monkeypatch.undo()
    _line_by_line(monkeypatch)
    slow = _outcome(path)
    assert _same(fast, slow), (fast, slow)
    if whole_takes_it:
        assert fast[0].shape == (4, 3) and fast[1].shape == (4, 3)


@pytest.mark.parametrize("name", sorted(p.name for p in SHARED_MESHES.glob("*.o[bf][jf]"))
                         if SHARED_MESHES.is_dir() else [])
def test_shared_meshes_read_as_the_line_by_line_reader_reads_them(name, monkeypatch):
    path = SHARED_MESHES / name
    fast = mesh_io.load_mesh(path)
    _line_by_line(monkeypatch)
    slow = mesh_io.load_mesh(path)
    assert _same(fast, slow)
    assert len(fast[0]) > 100 and len(fast[1]) == 2 * len(fast[0]) - 4      # closed genus 0


def test_large_obj_of_vertices_alone_is_refused_fast_in_little_memory(tmp_path):
    """50 MB of ``v 1 2 3`` lines and no face: one line, exit 2, within 5 s and 300 MB (it took
    17-24 s and 374 MB when every line was parsed first)."""
    path = tmp_path / "vertices.obj"
    with open(path, "wb") as out:
        for _ in range(63):
            out.write(b"v 1 2 3\n" * 100_000)
    assert path.stat().st_size >= 50_000_000
    env = dict(os.environ, PYTHONPATH=str(Path(mesh_io.__file__).parents[1]))
    stdout, stderr, peak = tmp_path / "stdout", tmp_path / "stderr", tmp_path / "peak"
    # The child's own peak (VmHWM of its process image, read as it exits): ru_maxrss would count
    # the pytest process it was forked from, hundreds of MB late in a full run.
    command = ("import atexit, re, runpy, sys\n"
               "atexit.register(lambda: open(%r, 'w').write(re.search(r'VmHWM:\\s+(\\d+)',"
               " open('/proc/self/status').read()).group(1)))\n"
               "sys.argv = ['sphere-nlp', %r, '-o', %r]\n"
               "runpy.run_module('sphere_nlp', run_name='__main__')\n" % (str(peak), str(path), str(tmp_path / "s.off")))
    with open(stdout, "wb") as out, open(stderr, "wb") as err:
        clock = time.perf_counter()
        child = subprocess.run([sys.executable, "-c", command], stdout=out, stderr=err, env=env)
        seconds = time.perf_counter() - clock
    peak_mb = int(peak.read_text()) / 1024
    peak.unlink()
    path.unlink()
    lines = stderr.read_text().strip().splitlines()
    assert child.returncode == 2 and stdout.read_bytes() == b""
    assert lines == ["sphere-nlp: error: cannot read %s as a mesh: it contains no triangles (no f lines)" % path]
    assert seconds < 5, seconds
    assert peak_mb < 300, peak_mb
    assert sorted(p.name for p in tmp_path.iterdir()) == ["stderr", "stdout"]      # no sphere, no temporary
