"""Reading meshes (anything trimesh reads) and writing results atomically.

Every writer goes to a temporary file in the destination folder and renames it into place, so a
failure or Ctrl-C never leaves a partial file, and an existing file is replaced only by a finished one.
"""

import codecs
import io
import json
import os
import re
import tempfile
from array import array
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from . import errors

MESH_FORMATS = (".off", ".obj", ".ply", ".glb", ".gltf")
# glTF stores positions as 32-bit floats (through trimesh's exporter); the others as text with 17 digits.
GLTF_FORMATS = (".glb", ".gltf")


def load_mesh(path):
    """Read a triangle mesh file, returning ``(vertices (n, 3) float, faces (t, 3) int)``.

    :func:`read_mesh` without its notes (the polygons it triangulated, if any).
    """
    vertices, faces, _ = read_mesh(path)
    return vertices, faces


def read_mesh(path):
    """Read a mesh file: ``(vertices (n, 3) float, faces (t, 3) int, notes)``.

    Vertices and faces are returned exactly as stored (no merging, no reordering). The reader is
    chosen by the file's first bytes (a FreeSurfer surface, such as ``lh.pial``, whatever its name),
    else by its extension in :data:`READERS` (OFF and OBJ by sphere_nlp's own strict readers, GIFTI
    through nibabel); other formats by trimesh. An OFF or OBJ file with faces of more than three
    corners is read again by trimesh, which splits them into triangles, and ``notes`` says so in
    one line (the split changes the target angles). For PLY the header's counts are checked
    against what trimesh read, which catches truncated files.

    Raises
    ------
    UnreadableMeshError
        Missing, empty, truncated or unparsable file, or no triangles in it.
    FaceIndexError
        An OBJ face refers to a vertex that does not exist.
    """
    path = Path(path)
    if not path.exists():
        raise errors.UnreadableMeshError("cannot read %s: no such file" % path)
    if not path.is_file():
        raise errors.UnreadableMeshError("cannot read %s: not a file" % path)
    try:
        if path.stat().st_size == 0:
            raise errors.UnreadableMeshError("cannot read %s: the file is empty" % path)
        suffix = path.suffix.lower()
        notes = []
        with open(path, "rb") as handle:
            magic = handle.read(3)
        if magic in FREESURFER_MAGICS:          # lh.pial, lh.white, ...: no extension to go by
            vertices, faces = read_freesurfer(path)
        else:
            # The first bytes decide whether the file can be this format at all, before a large file is
            # parsed (a 50 MB file of digits named .off took 15 s and 1.9 GB to reject).
            _check_header(path, suffix)
            try:
                vertices, faces = READERS.get(suffix, _load_with_trimesh)(path)
            except PolygonFacesError as exc:
                vertices, faces = _load_with_trimesh(path, split=True)
                notes.append("split %s of more than 3 corners into triangles (%d faces became %d "
                             "triangles; the split sets their target angles)"
                             % ("%d face(s)" % exc.count if exc.count else "the faces", exc.faces, len(faces)))
    except OSError as exc:                      # unreadable (permissions, I/O error, ...)
        raise errors.UnreadableMeshError("cannot read %s: %s" % (path, exc.strerror or exc)) from None
    if len(faces) == 0 or len(vertices) == 0:
        raise errors.UnreadableMeshError("cannot read %s as a mesh: it contains no triangles "
                                         "(empty or truncated?)" % path)
    return vertices, faces, notes


class PolygonFacesError(errors.UnreadableMeshError):
    """A strict reader met faces of more than three corners (``count`` of its ``faces``)."""

    def __init__(self, message, count, faces):
        super().__init__(message)
        self.count, self.faces = count, faces


# FreeSurfer's binary surfaces start with a 3-byte magic number: triangles (0xFFFFFE), and the old
# quadrangle formats (0xFFFFFF, 0xFFFFFD), which are refused by name.
FREESURFER_TRIANGLES = b"\xff\xff\xfe"
FREESURFER_MAGICS = (FREESURFER_TRIANGLES, b"\xff\xff\xff", b"\xff\xff\xfd")


def read_freesurfer(path):
    """Read a FreeSurfer triangle surface (``lh.pial``, ``rh.white``, ``lh.sphere``, ...).

    The format: the magic 0xFFFFFE, a creation line and an empty line, the vertex and face counts
    (big-endian int32), then float32 x y z per vertex and int32 a b c per face (big-endian); any
    tags after the faces are ignored. Coordinates are float32 in the file and exact in the result.

    Raises UnreadableMeshError for a quadrangle surface, a truncated file or impossible counts.
    """
    path = Path(path)
    with open(path, "rb") as handle:
        data = handle.read()
    if data[:3] != FREESURFER_TRIANGLES:
        raise errors.UnreadableMeshError("cannot read %s: a FreeSurfer quadrangle surface (magic %s); only "
                                         "the triangle format (0xFFFFFE) is read" % (path, data[:3].hex().upper()))
    # The creation line ends in "\n\n" (FreeSurfer's own writers and nibabel's).
    end = data.find(b"\n\n", 3, 3 + 4096)
    if end < 0:
        raise errors.UnreadableMeshError("cannot read %s: a FreeSurfer surface without the line that "
                                         "ends its header" % path)
    offset = end + 2
    if len(data) < offset + 8:
        raise errors.UnreadableMeshError("cannot read %s: truncated (no vertex and face counts)" % path)
    n_vertices, n_faces = (int(c) for c in np.frombuffer(data, ">i4", 2, offset))
    if n_vertices <= 0 or n_faces <= 0:
        raise errors.UnreadableMeshError("cannot read %s as a mesh: the header declares %d vertices and %d "
                                         "faces" % (path, n_vertices, n_faces))
    offset += 8
    needed = offset + 12 * (n_vertices + n_faces)
    if len(data) < needed:
        raise errors.UnreadableMeshError("cannot read %s: truncated (header promises %d vertices and %d faces: "
                                         "%d bytes, the file has %d)" % (path, n_vertices, n_faces, needed,
                                                                         len(data)))
    vertices = np.frombuffer(data, ">f4", 3 * n_vertices, offset).reshape(-1, 3).astype(float)
    faces = np.frombuffer(data, ">i4", 3 * n_faces, offset + 12 * n_vertices).reshape(-1, 3).astype(np.int64)
    return vertices, faces


def read_gifti(path):
    """Read a GIFTI surface (``.surf.gii``): its point set and its triangles, through nibabel.

    Raises UnreadableMeshError without nibabel (the ``neuro`` extra), for a file nibabel cannot
    parse, or for one without both arrays.
    """
    path = Path(path)
    try:
        import nibabel
    except ImportError:
        raise errors.UnreadableMeshError("cannot read %s: GIFTI files are read through nibabel, which is not "
                                         "installed (pip install 'sphere_nlp[neuro]')" % path) from None
    try:
        image = nibabel.load(str(path))
        arrays = {nibabel.nifti1.intent_codes.label[a.intent]: a.data for a in image.darrays}
    except Exception as exc:                    # nibabel raises many types for bad files
        detail = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise errors.UnreadableMeshError("cannot read %s as GIFTI (corrupt or truncated?): %s"
                                         % (path, detail)) from None
    missing = [name for name in ("pointset", "triangle") if name not in arrays]
    if missing:
        raise errors.UnreadableMeshError("cannot read %s as a mesh: a GIFTI file without a %s array (it has %s)"
                                         % (path, " or ".join(missing), ", ".join(sorted(arrays)) or "none"))
    vertices = np.asarray(arrays["pointset"], float).reshape(-1, 3)
    faces = np.asarray(arrays["triangle"], np.int64).reshape(-1, 3)
    return vertices, faces




# Bytes read to recognise a file's format (a text header, or a PLY header up to end_header).
HEADER_BYTES = 1 << 16
# OBJ statements sphere_nlp knows (v and f are read, the others skipped).
OBJ_STATEMENTS = ("v", "f", "vt", "vn", "vp", "g", "o", "s", "usemtl", "mtllib", "l", "p", "cstype",
                  "deg", "curv", "surf", "end")


def _decode(data):
    """Text of a file's bytes: UTF-8 (with or without a byte-order mark), UTF-16/32 with a BOM, or
    Latin-1 for anything else. A BOM must not become part of the first word (an OBJ's first ``v``
    line would be skipped and every face index shift)."""
    for bom, codec in ((codecs.BOM_UTF32_LE, "utf-32"), (codecs.BOM_UTF32_BE, "utf-32"),
                       (codecs.BOM_UTF8, "utf-8-sig"), (codecs.BOM_UTF16_LE, "utf-16"),
                       (codecs.BOM_UTF16_BE, "utf-16")):
        if data.startswith(bom):
            return data.decode(codec, "replace")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        if exc.start >= len(data) - 3:           # a header cut inside a multi-byte character
            return data[:exc.start].decode("utf-8")
        return data.decode("latin-1")


def _check_header(path, suffix):
    """Reject a file whose first bytes cannot start a mesh of its format (cheap, bounded memory)."""
    with open(path, "rb") as handle:
        head = handle.read(HEADER_BYTES)
        size = os.fstat(handle.fileno()).st_size
    if suffix in (".off", ".obj"):
        if b"\0" in head and not head.startswith((codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE)):
            raise errors.UnreadableMeshError("cannot read %s: not a text %s file (binary data)"
                                             % (path, suffix[1:].upper()))
        lines = [line.split("#", 1)[0].split() for line in _decode(head).splitlines()]
        if size > len(head):
            lines = lines[:-1]                  # the last line may be cut
        words = [w for w in lines if w]
        if suffix == ".off":
            if words and not words[0][0].upper().endswith("OFF"):
                raise errors.UnreadableMeshError("cannot read %s: not an OFF file (it starts with %r, not an "
                                                 "OFF header)" % (path, words[0][0][:20]))
        elif size > len(head) and not any(w[0] in OBJ_STATEMENTS for w in words):
            raise errors.UnreadableMeshError("cannot read %s: not an OBJ file (no v or f lines in its first "
                                             "%d KB)" % (path, HEADER_BYTES >> 10))
    elif suffix == ".ply":
        if not head.startswith(b"ply"):
            raise errors.UnreadableMeshError("cannot read %s: not a PLY file (it does not start with 'ply')"
                                             % path)
        end = head.find(b"end_header")
        if end < 0:
            raise errors.UnreadableMeshError("cannot read %s as a mesh: the PLY header has no end_header "
                                             "(in its first %d KB)" % (path, HEADER_BYTES >> 10))
        if b"format ascii" in head[:end]:
            # The body's first line must be numbers: text that is not a PLY body is refused here,
            # before trimesh reads the whole file.
            after = head[end:].split(b"\n", 1)
            first = next((line for line in (after[1] if len(after) > 1 else b"").split(b"\n")
                          if line.strip()), b"")
            try:
                [float(word) for word in first.split()]
            except ValueError:
                raise errors.UnreadableMeshError("cannot read %s: not a PLY file (the first line after its "
                                                 "ASCII header is not numbers)" % path) from None
    elif suffix == ".stl":
        # Binary STL: an 80-byte header, a triangle count, 50 bytes per triangle; ASCII STL: "solid".
        binary_ok = size >= 84 and size == 84 + 50 * int.from_bytes(head[80:84], "little")
        if not binary_ok:
            lines = [line.strip().lower() for line in head.split(b"\n") if line.strip()]
            # ASCII STL: "solid NAME", then "facet normal ..." (or "endsolid" for an empty one).
            if not (lines and lines[0].startswith(b"solid")
                    and (len(lines) < 2 or lines[1].startswith((b"facet", b"endsolid")))):
                raise errors.UnreadableMeshError("cannot read %s: not an STL file (neither ASCII, starting with "
                                                 "'solid' and a facet, nor binary with a consistent triangle "
                                                 "count)" % path)


def _load_with_trimesh(path, split=False):
    """Formats other than OFF and OBJ, through trimesh (with PLY header counts checked); with
    ``split``, faces of more than 3 corners are accepted as trimesh splits them."""
    import trimesh

    try:
        loaded = trimesh.load(str(path), process=False, force="mesh")
        vertices = np.asarray(loaded.vertices, dtype=float).reshape(-1, 3)
        faces = np.asarray(loaded.faces, dtype=np.int64).reshape(-1, 3)
    except Exception as exc:  # trimesh raises many types for bad files
        detail = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise errors.UnreadableMeshError("cannot read %s as a mesh (corrupt or truncated?): %s"
                                         % (path, detail)) from None
    if path.suffix.lower() == ".ply":
        _check_ply_counts(path, len(vertices), len(faces), split)
    return vertices, faces


def _check_ply_counts(path, n_vertices, n_faces, split=False):
    """Compare a PLY header's element counts with what was read.

    trimesh reads a truncated ASCII PLY without complaint (it returns the faces that are there) and
    triangulates polygons; both show up as a face count different from the header's.
    """
    with open(path, "rb") as handle:
        head = handle.read(HEADER_BYTES)
    end = head.find(b"end_header")
    if end < 0:
        raise errors.UnreadableMeshError("cannot read %s as a mesh: PLY header has no end_header" % path)
    header = head[:end].decode("ascii", "replace").split("\n")
    counts = {}
    for line in header:
        words = line.split()
        if len(words) == 3 and words[0] == "element" and words[2].isdigit():
            counts[words[1]] = int(words[2])
    promised_v, promised_f = counts.get("vertex"), counts.get("face")
    if promised_v is not None and n_vertices < promised_v:
        raise errors.UnreadableMeshError("cannot read %s: truncated (header promises %d vertices, found %d)"
                                         % (path, promised_v, n_vertices))
    if promised_f is not None and n_faces < promised_f:
        raise errors.UnreadableMeshError("cannot read %s: truncated (header promises %d faces, found %d)"
                                         % (path, promised_f, n_faces))
    if promised_f is not None and n_faces > promised_f and not split:
        raise PolygonFacesError("cannot read %s: it has faces with more than 3 corners (%d faces triangulate "
                                "into %d)" % (path, promised_f, n_faces), None, promised_f)


def _text_lines(path, kind):
    """The file's lines one at a time, as (line number, words before any '#'), in bounded memory:
    a large file that is not a mesh is rejected at its first bad line without being held whole.
    Rejects binary content (a NUL character)."""
    with open(path, "rb") as raw:
        head = raw.read(4)
        raw.seek(0)
        encoding = "utf-8"
        for bom, codec in ((codecs.BOM_UTF32_LE, "utf-32"), (codecs.BOM_UTF32_BE, "utf-32"),
                           (codecs.BOM_UTF8, "utf-8-sig"), (codecs.BOM_UTF16_LE, "utf-16"),
                           (codecs.BOM_UTF16_BE, "utf-16")):
            if head.startswith(bom):
                encoding = codec
                break
        # Numbers are ASCII; other characters (in comments) need not decode.
        with io.TextIOWrapper(raw, encoding=encoding, errors="replace") as text:
            for number, line in enumerate(text, 1):
                if "\0" in line:
                    raise errors.UnreadableMeshError("cannot read %s: not a text %s file (binary data)"
                                                     % (path, kind))
                words = line.split("#", 1)[0].split()
                if words:
                    yield number, words


def _floats(words, path, line_number, what):
    try:
        return [float(w) for w in words]
    except ValueError:
        raise errors.UnreadableMeshError("cannot read %s: line %d: %s is not a number"
                                         % (path, line_number, what)) from None


# The whole-buffer readers below parse a well-formed OFF or OBJ file with numpy at tens of MB/s
# (about 10x the line-by-line readers). Anything they cannot vouch for (an unusual encoding, a NUL,
# a character that is not part of a number, a polygon, a bad index) sends the file to the
# line-by-line reader, whose error names the line: both always return the same arrays.

# Bytes that become a space: str.split() separates words at them too.
_SPACES = bytes.maketrans(b"\t\v\f\x1c\x1d\x1e\x1f", b" " * 7)
# Characters of the numbers the whole-buffer readers take (as float() spells them, nan and inf
# included); any other character leaves the file to the line-by-line reader.
_FLOAT_BYTES = np.zeros(256, bool)
_FLOAT_BYTES[list(b"0123456789+-.eE \nnNaAiIfFtTyY")] = True
_INT_BYTES = np.zeros(256, bool)
_INT_BYTES[list(b"0123456789+- \n")] = True
# UTF-8 spaces beyond ASCII (U+0085, U+00A0, U+1680, U+2000-200A, U+2028/9, U+202F, U+205F, U+3000).
_UNICODE_SPACE = re.compile(rb"\xc2[\x85\xa0]|\xe1\x9a\x80|\xe2\x80[\x80-\x8a\xa8\xa9\xaf]|\xe2\x81\x9f|"
                            rb"\xe3\x80\x80")
# Bytes read at a time when an OBJ file is searched for its first face line.
SCAN_BYTES = 1 << 24


def _whole_text(path):
    """The file's bytes as one buffer of ``\\n``-ended lines, comments removed, every separator a
    space and no leading spaces; or None for what only the line-by-line reader handles (UTF-16/32,
    NUL bytes)."""
    with open(path, "rb") as handle:
        data = handle.read()
    if data.startswith(codecs.BOM_UTF8):
        data = data[len(codecs.BOM_UTF8):]
    elif data.startswith((codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE, codecs.BOM_UTF32_BE)) or b"\0" in data:
        return None
    if b"\r" in data:                           # the line ends Python's text files accept
        data = data.replace(b"\r\n", b"\n").replace(b"\r", b"\n")
    if b"#" in data:
        data = re.sub(rb"#[^\n]*", b"", data)
    if _UNICODE_SPACE.search(data):             # words the decoded text would split at
        return None
    data = data.translate(_SPACES)
    if data.startswith(b" ") or b"\n " in data:
        data = re.sub(rb"(?m)^ +", b"", data)
    return data if data.endswith(b"\n") else data + b"\n"


def _line_bounds(buffer):
    """(start, end) byte offsets of every line of a ``\\n``-ended buffer; end is its ``\\n``."""
    ends = np.flatnonzero(buffer == ord("\n"))
    starts = np.empty_like(ends)
    starts[:1] = 0
    starts[1:] = ends[:-1] + 1
    return starts, ends


def _numbers(buffer, starts, allowed, dtype):
    """The numbers on the lines of ``buffer`` starting at ``starts`` (offsets into it, ascending,
    the lines between them holding no numbers), as (flat values, count per line); None when a
    character is not in ``allowed`` or a word does not read as one number."""
    if not allowed[buffer].all():
        return None
    separator = (buffer == ord(" ")) | (buffer == ord("\n"))
    word_starts = np.flatnonzero(~separator[1:] & separator[:-1]) + 1
    if len(buffer) and not separator[0]:
        word_starts = np.r_[0, word_starts]
    counts = np.diff(np.searchsorted(word_starts, np.r_[starts, len(buffer)]))
    try:
        values = np.fromstring(buffer.tobytes(), dtype=dtype, sep=" ")
    except ValueError:                          # a word that is not a number
        return None
    if len(values) != len(word_starts):         # a word read as two numbers ("1.2.3")
        return None
    return values, counts


def _first_three(values, counts):
    """The first three numbers of each line (every line has at least three)."""
    if (counts == 3).all():
        return values.reshape(-1, 3)
    first = np.cumsum(counts) - counts
    return values[first[:, None] + np.arange(3)]


def _obj_has_faces(path):
    """Search an OBJ file for a face line in bounded memory: (has an ``f`` line, has any OBJ
    statement). A file of vertices alone is rejected after one fast pass instead of a parse."""
    with open(path, "rb") as handle:
        head = handle.read(4)
        if head.startswith((codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE, codecs.BOM_UTF32_BE)):
            return True, True                   # the line-by-line reader decodes these
        handle.seek(0)
        face = re.compile(rb"[\n\r][ \t\v\f]*f[ \t\v\f\r\n]")
        statement = re.compile(rb"[\n\r][ \t\v\f]*(?:%s)[ \t\v\f\r\n]"
                               % b"|".join(word.encode() for word in OBJ_STATEMENTS))
        known = False
        tail = b"\n"                            # the first line starts a line too
        while True:
            chunk = handle.read(SCAN_BYTES)
            if not chunk:
                return False, known
            text = tail + chunk + (b"" if len(chunk) == SCAN_BYTES else b"\n")
            if face.search(text):
                return True, True
            known = known or statement.search(text) is not None
            # A line cut by the chunk's end is searched again with the next chunk.
            cut = max(text.rfind(b"\n"), text.rfind(b"\r"))
            tail = text[cut:][:HEADER_BYTES] if cut >= 0 else b""


def _read_obj_whole(path):
    """``(vertices, faces)`` of an OBJ file by :func:`_whole_text`, or None (see above)."""
    data = _whole_text(path)
    if data is None:
        return None
    buffer = np.frombuffer(data, np.uint8)
    starts, ends = _line_bounds(buffer)
    second = buffer[np.minimum(starts + 1, len(buffer) - 1)]
    word_ends = (second == ord(" ")) | (second == ord("\n"))
    first = buffer[starts]
    is_vertex = (first == ord("v")) & word_ends
    is_face = (first == ord("f")) & word_ends
    lengths = ends - starts + 1

    def lines_of(selected):
        """The selected lines as one buffer without their first word, and their starts in it."""
        part = buffer[np.repeat(selected, lengths)]
        part_starts = np.cumsum(lengths[selected]) - lengths[selected]
        part[part_starts] = ord(" ")
        return part, part_starts

    part, part_starts = lines_of(is_vertex)
    read = _numbers(part, part_starts, _FLOAT_BYTES, float)
    if read is None or (read[1] < 3).any():
        return None
    vertices = _first_three(*read)
    part, part_starts = lines_of(is_face)
    if (part == ord("/")).any():                # 1/4/2: the vertex is the first number
        part = np.frombuffer(re.sub(rb"/[^ \n]*", b"", part.tobytes()), np.uint8)
        part_starts, _ = _line_bounds(part)
    read = _numbers(part, part_starts, _INT_BYTES, np.int64)
    if read is None or (read[1] != 3).any():
        return None
    faces = read[0].reshape(-1, 3)
    if (faces < 0).any():                       # relative to the vertices read before the face
        before = (np.cumsum(is_vertex) - is_vertex)[is_face]
        faces = np.where(faces < 0, faces + before[:, None], faces - 1)
    else:
        faces = faces - 1
    if ((faces < 0) | (faces >= len(vertices))).any():
        return None                             # the line-by-line reader names the face's line
    return vertices, faces


def _read_off_body_whole(path, skip, n_vertices, n_faces, truncated):
    """``(vertices, faces)`` of an OFF file's body after its first ``skip`` lines, or None (see
    above); raises ``truncated(lines found)`` for a file with fewer lines than its header promises,
    before any number is read."""
    data = _whole_text(path)
    if data is None:
        return None
    at = 0
    for _ in range(skip):
        at = data.find(b"\n", at) + 1
        if at == 0:
            return None
    data = data[at:]
    if b"\n\n" in data:                         # blank lines carry nothing in an OFF body
        data = re.sub(rb"\n\n+", b"\n", data)
    data = data[1:] if data.startswith(b"\n") else data
    found = data.count(b"\n")
    if found < n_vertices + n_faces:            # found before a number is read
        raise truncated(found)
    buffer = np.frombuffer(data, np.uint8)
    starts, ends = _line_bounds(buffer)

    def numbers(first, count, allowed, dtype):
        """The numbers of lines first .. first + count - 1 (all of them hold words)."""
        begin, end = starts[first], ends[first + count - 1] + 1
        return _numbers(buffer[begin:end], starts[first:first + count] - begin, allowed, dtype)

    read = numbers(0, n_vertices, _FLOAT_BYTES, float)
    if read is None or (read[1] < 3).any():
        return None
    vertices = _first_three(*read)
    read = numbers(n_vertices, n_faces, _INT_BYTES, np.int64)
    if read is None or (read[1] != 4).any():
        return None                             # polygons, colours: read line by line
    faces = read[0].reshape(-1, 4)
    limits = np.iinfo(np.int64)
    if (faces[:, 0] != 3).any() or ((faces == limits.max) | (faces == limits.min)).any():
        return None                             # an index beyond 64 bits is clipped to a limit
    return vertices, faces[:, 1:].copy()


def read_off(path):
    """Read an ASCII OFF file (also COFF, NOFF, ... headers) strictly.

    The header's counts must be met exactly: fewer vertex or face lines means a truncated file.
    Every face must be a triangle (``3 a b c``; colour values after the indices are ignored).

    Returns
    -------
    vertices : (n, 3) float array
    faces : (t, 3) int64 array
        Indices as stored (range checks come later, in validation).

    Raises
    ------
    UnreadableMeshError

    Examples
    --------
    >>> import tempfile, os
    >>> with tempfile.TemporaryDirectory() as d:
    ...     p = os.path.join(d, "t.off")
    ...     _ = open(p, "w").write("OFF\\n4 4 0\\n0 0 0\\n1 0 0\\n0 1 0\\n0 0 1\\n"
    ...                            "3 0 2 1\\n3 0 1 3\\n3 0 3 2\\n3 1 2 3\\n")
    ...     V, F = read_off(p)
    >>> V.shape, F.tolist()[0]
    ((4, 3), [0, 2, 1])
    """
    path = Path(path)
    size = path.stat().st_size
    lines = _text_lines(path, "OFF")
    first = next(lines, None)
    if first is None or not first[1][0].upper().endswith("OFF"):
        raise errors.UnreadableMeshError("cannot read %s: not an OFF file (no OFF header)" % path)
    counts_line, counts = first[0], first[1][1:]    # "OFF n t e" on one line is allowed too
    if not counts:
        second = next(lines, None)
        if second is None:
            raise errors.UnreadableMeshError("cannot read %s: truncated (no vertex and face counts)" % path)
        counts_line, counts = second
    try:
        n_vertices, n_faces = int(counts[0]), int(counts[1])
    except (ValueError, IndexError):
        raise errors.UnreadableMeshError("cannot read %s: the OFF header's counts %r are not two integers"
                                         % (path, " ".join(counts)[:60])) from None
    if n_vertices <= 0 or n_faces <= 0:
        raise errors.UnreadableMeshError("cannot read %s as a mesh: the header declares %d vertices and %d "
                                         "faces" % (path, n_vertices, n_faces))

    def truncated(found):
        found_v = min(found, n_vertices)
        found_f = max(found - n_vertices, 0)
        return errors.UnreadableMeshError("cannot read %s: truncated (header promises %d vertices and %d "
                                          "faces, found %d and %d)"
                                          % (path, n_vertices, n_faces, found_v, found_f))

    # A vertex line takes at least 6 bytes ("0 0 0\n"), a face line 8 ("3 0 1 2\n"): counts the file
    # cannot hold are found without allocating for them.
    if 6 * n_vertices + 8 * n_faces > size:
        raise truncated(sum(1 for _ in lines))
    whole = _read_off_body_whole(path, counts_line, n_vertices, n_faces, truncated)
    if whole is not None:
        lines.close()
        return whole
    vertices = np.empty((n_vertices, 3))
    found = 0
    for i, (line_number, words) in zip(range(n_vertices), lines):
        if len(words) < 3:
            raise errors.UnreadableMeshError("cannot read %s: line %d: vertex %d has %d coordinate(s), "
                                             "expected 3" % (path, line_number, i, len(words)))
        vertices[i] = _floats(words[:3], path, line_number, "a vertex coordinate")
        found += 1
    faces = np.empty((n_faces, 3), np.int64)
    polygons = []
    for i, (line_number, words) in zip(range(n_faces), lines):
        found += 1
        try:
            size = int(words[0])
            indices = [int(w) for w in words[1:1 + size]] if size >= 0 else []
        except ValueError:
            raise errors.UnreadableMeshError("cannot read %s: line %d: face %d has a non-integer index"
                                             % (path, line_number, i)) from None
        if len(indices) < size:
            raise errors.UnreadableMeshError("cannot read %s: line %d: face %d promises %d indices, has %d"
                                             % (path, line_number, i, size, len(indices)))
        if size != 3:
            polygons.append((i, size))
            continue
        try:
            faces[i] = indices
        except OverflowError:                   # an index beyond 64 bits cannot name a vertex
            raise errors.FaceIndexError("%s: line %d: face %d refers to vertex %s, which does not exist "
                                        "(the file has %d vertices)"
                                        % (path, line_number, i, _too_large(indices), n_vertices)) from None
    if found < n_vertices + n_faces:
        raise truncated(found)
    _reject_polygons(path, polygons, n_faces)
    return vertices, faces


def read_obj(path):
    """Read the geometry of a Wavefront OBJ file strictly: ``v`` and ``f`` lines, nothing else.

    Texture and normal references (``f 1/4/2 ...``) and negative (relative) indices are understood;
    all other statements are ignored. Vertex and face order are kept. A file without an ``f`` line
    is refused after one fast pass over its bytes, before any number is read.

    Returns
    -------
    vertices : (n, 3) float array
    faces : (t, 3) int64 array (0-based)

    Raises
    ------
    UnreadableMeshError
        Unparsable lines, polygons, no faces.
    FaceIndexError
        A face refers to a vertex that does not exist.
    """
    path = Path(path)
    has_faces, known = _obj_has_faces(path)
    if not has_faces:
        if not known:
            raise errors.UnreadableMeshError("cannot read %s: not an OBJ file (no v or f lines)" % path)
        raise errors.UnreadableMeshError("cannot read %s as a mesh: it contains no triangles (no f lines)"
                                         % path)
    whole = _read_obj_whole(path)
    if whole is not None:
        return whole
    # Line by line, for what the whole-buffer reader leaves (and to name the line of a defect).
    # Compact arrays, not lists of lists: memory stays a small multiple of the mesh's own size.
    vertices, faces, face_lines = array("d"), array("q"), array("q")
    polygons = []
    known = False
    n_vertices = 0
    for line_number, words in _text_lines(path, "OBJ"):
        if words[0] == "v":
            known = True
            if len(words) < 4:
                raise errors.UnreadableMeshError("cannot read %s: line %d: vertex %d has %d coordinate(s), "
                                                 "expected 3" % (path, line_number, n_vertices + 1,
                                                                 len(words) - 1))
            vertices.extend(_floats(words[1:4], path, line_number, "a vertex coordinate"))
            n_vertices += 1
        elif words[0] == "f":
            known = True
            n_faces = len(face_lines)
            try:
                corners = [int(w.split("/")[0]) for w in words[1:]]
            except ValueError:
                raise errors.UnreadableMeshError("cannot read %s: line %d: face %d has a non-integer index"
                                                 % (path, line_number, n_faces)) from None
            if len(corners) != 3:
                polygons.append((n_faces, len(corners)))
                corners = (corners + [0, 0, 0])[:3]
            # OBJ numbers vertices from 1; negative numbers count back from the latest vertex.
            corners = [c - 1 if c > 0 else n_vertices + c if c < 0 else -1 for c in corners]
            try:
                faces.extend(corners)
            except OverflowError:               # an index beyond 64 bits cannot name a vertex
                raise errors.FaceIndexError("%s: line %d: face %d refers to vertex %s, which does not exist "
                                            "(the file has %d vertices, numbered from 1)"
                                            % (path, line_number, n_faces, _too_large(corners) + 1,
                                               n_vertices)) from None
            face_lines.append(line_number)
        elif words[0] in OBJ_STATEMENTS:
            known = True
    if not known:
        raise errors.UnreadableMeshError("cannot read %s: not an OBJ file (no v or f lines)" % path)
    _reject_polygons(path, polygons, len(face_lines))
    vertices = np.frombuffer(vertices, float).reshape(-1, 3).copy()
    faces = np.frombuffer(faces, np.int64).reshape(-1, 3).copy()
    bad = (faces < 0) | (faces >= len(vertices))
    if bad.any():
        i = int(np.flatnonzero(bad.any(axis=1))[0])
        raise errors.FaceIndexError("%s: line %d: face %d refers to a vertex that does not exist "
                                    "(the file has %d vertices, numbered from 1)"
                                    % (path, face_lines[i], i, len(vertices)))
    return vertices, faces


# The file formats sphere_nlp reads itself, by extension (FreeSurfer's, which has none, by its first
# bytes); any other extension goes to trimesh.
READERS = {".off": read_off, ".obj": read_obj, ".gii": read_gifti}


def _too_large(indices):
    """The first index that does not fit in 64 bits, or None."""
    return next((k for k in indices if not -2 ** 63 <= k < 2 ** 63), None)


def _reject_polygons(path, polygons, n_faces=None):
    # read_mesh catches this and has trimesh read and split the polygons; the strict readers
    # themselves stay triangles-only.
    short = [(i, size) for i, size in polygons if size < 3]
    if short:
        i, size = short[0]
        raise errors.UnreadableMeshError("cannot read %s: face %d has %d corner(s): a face needs at least 3"
                                         % (path, i, size))
    if polygons:
        i, size = polygons[0]
        raise PolygonFacesError("cannot read %s: %d face(s) are not triangles (e.g. face %d has %d corners)"
                                % (path, len(polygons), i, size), len(polygons), n_faces)


# The open output_transaction()'s staged files, [(temporary path, destination)], or None.
_staged = None


@contextmanager
def atomic_output(path, mode="w"):
    """Open a temporary file beside ``path``; rename it to ``path`` only if the block succeeds.

    Inside :func:`output_transaction` the finished temporary file is staged instead, and renamed
    together with the transaction's other outputs when the transaction ends.
    """
    from . import interrupts

    path = Path(path)
    directory = path.parent if str(path.parent) else Path(".")
    # A signal some library caught (and went on) still stops every write.
    interrupts.check_before_write()
    fd, tmp = tempfile.mkstemp(prefix="." + path.name + ".", suffix=".tmp", dir=directory)
    try:
        # mkstemp makes the file private (0600); give it the permissions a plain open() would.
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        with os.fdopen(fd, mode) as handle:
            yield handle
        interrupts.check_before_write()
        if _staged is not None:
            _staged.append((tmp, path))
        else:
            os.replace(tmp, path)
    except BaseException:
        _remove_quietly(tmp)
        raise


def _remove_quietly(path):
    try:
        os.unlink(path)
    except OSError:
        pass


@contextmanager
def output_transaction():
    """Write several outputs all together or not at all.

    Every :func:`atomic_output` inside the block (``write_mesh``, ``write_json``, ``write_npz``, the
    picture) goes to a temporary file beside its destination. Only when the whole block has
    succeeded are they renamed into place, one after the other with signals deferred
    (:func:`sphere_nlp.interrupts.defer_signals`); if a rename fails or a signal arrived meanwhile,
    the renamed ones are undone (an existing file comes back from a hard link kept until the end)
    and the exception is raised. On any exception, the temporary files are removed: nothing is
    created or replaced. Nested transactions join the outer one.

    Example
    -------
    >>> import tempfile, os
    >>> from sphere_nlp.shapes import octahedron
    >>> with tempfile.TemporaryDirectory() as d:
    ...     try:
    ...         with output_transaction():
    ...             write_mesh(os.path.join(d, "a.off"), *octahedron())
    ...             raise RuntimeError("a later step failed")
    ...     except RuntimeError:
    ...         pass
    ...     os.listdir(d)
    []
    """
    if _staged is not None:
        yield
        return
    with staged_outputs() as staged:
        yield
    _commit(staged)


@contextmanager
def staged_outputs():
    """Like :func:`output_transaction`, but the finished temporary files are left for the caller,
    as the list this yields of (temporary path, destination), to rename with :func:`commit_staged`
    (or remove): a batch's worker stages a mesh's files, and the batch renames them when it records
    the mesh. On any exception the temporary files are removed."""
    global _staged
    if _staged is not None:
        raise RuntimeError("staged_outputs() inside another transaction")
    staged = _staged = []
    try:
        yield staged
    except BaseException:
        _staged = None
        for tmp, _ in staged:
            _remove_quietly(tmp)
        raise
    _staged = None


@contextmanager
def created_folder(folder):
    """Create ``folder`` (and its missing parents) for the block; if the block raises, remove again
    the folders it created, when they are empty: a run that writes nothing leaves no folder."""
    folder = Path(folder)
    missing = []
    for parent in (folder, *folder.parents):
        if parent.exists():
            break
        missing.append(parent)
    folder.mkdir(parents=True, exist_ok=True)
    try:
        yield folder
    except BaseException:
        for path in missing:                    # deepest first
            try:
                path.rmdir()
            except OSError:
                break
        raise


def commit_staged(staged, remove=()):
    """Rename files staged by :func:`staged_outputs` into place in their order, after removing the
    paths ``remove`` (outputs of an earlier run that this one replaces with nothing). Signals are
    deferred meanwhile (:func:`sphere_nlp.interrupts.defer_signals`); the caller decides what a
    pending one means afterwards."""
    from . import interrupts

    with interrupts.defer_signals():
        for path in remove:
            _remove_quietly(path)
        for tmp, path in staged:
            os.replace(tmp, path)


def discard_staged(staged):
    """Remove files staged by :func:`staged_outputs` that will not be committed."""
    for tmp, _ in staged:
        _remove_quietly(tmp)


def _commit(staged):
    """Rename staged files into place, all or none (see :func:`output_transaction`)."""
    from . import interrupts

    done = []                                   # (destination, backup of the file it replaced or None)
    with interrupts.defer_signals():
        try:
            for tmp, path in staged:
                backup = None
                if os.path.lexists(path):
                    backup = tempfile.mktemp(prefix="." + path.name + ".", suffix=".tmp", dir=path.parent)
                    try:
                        os.link(path, backup, follow_symlinks=False)
                    except OSError:             # no hard links here: that file cannot come back
                        backup = False
                os.replace(tmp, path)
                done.append((path, backup))
            interrupts.raise_if_interrupted()
            interrupts.committed()
        except BaseException:
            for path, backup in reversed(done):
                if backup:
                    os.replace(backup, path)
                elif backup is None:            # the file did not exist before
                    _remove_quietly(path)
            for tmp, _ in staged[len(done):]:
                _remove_quietly(tmp)
            raise
        for _, backup in done:
            if backup:
                _remove_quietly(backup)


def check_mesh_path(path):
    """Raise UsageError unless ``path`` has a mesh extension we can write."""
    if Path(path).suffix.lower() not in MESH_FORMATS:
        raise errors.UsageError("cannot write %s: output must end in %s" % (path, ", ".join(MESH_FORMATS)))


def write_mesh(path, vertices, faces, corner_uv=None, material=None):
    """Write a triangle mesh as OFF, OBJ or PLY (ASCII), or glTF (.glb, .gltf), chosen by the extension.

    Coordinates are written with 17 significant digits, so they read back bit for bit and the
    certificate computed before writing holds for the file; glTF holds 32-bit floats (see
    :meth:`sphere_nlp.api.SphericalParameterization.write` for how a sphere is certified for it).

    Parameters
    ----------
    path : str or Path
    vertices : (n, 3) float array
    faces : (t, 3) int array
    corner_uv : (t, 3, 2) float array, optional
        Texture coordinates per corner (e.g. :func:`sphere_nlp.texture.spherical_uv`), OBJ only:
        written as ``vt`` lines (one per distinct (u, v)) and ``f v/vt`` faces.
    material : str, optional
        OBJ only: the name of an MTL file beside the OBJ (see :func:`write_material`), referenced by
        ``mtllib`` and used for every face, so viewers show its texture.

    Examples
    --------
    >>> import tempfile, os
    >>> from sphere_nlp.shapes import octahedron
    >>> from sphere_nlp.texture import spherical_uv
    >>> V, F = octahedron()
    >>> with tempfile.TemporaryDirectory() as d:
    ...     write_mesh(os.path.join(d, "o.obj"), V, F, spherical_uv(V, F))
    ...     lines = open(os.path.join(d, "o.obj")).read().splitlines()
    >>> sum(line.startswith("vt ") for line in lines), [line for line in lines if line[0] == "f"][:2]
    (13, ['f 1/1 3/2 5/3', 'f 3/2 2/4 5/5'])
    """
    check_mesh_path(path)
    suffix = Path(path).suffix.lower()
    vertices = np.asarray(vertices, float)
    faces = np.asarray(faces, np.int64)
    if corner_uv is not None:
        if suffix != ".obj":
            raise errors.UsageError("cannot write texture coordinates to %s: only OBJ carries them" % path)
        corner_uv = np.asarray(corner_uv, float)
        if corner_uv.shape != faces.shape + (2,):
            raise ValueError("corner_uv must have shape (t, 3, 2), got %s" % (corner_uv.shape,))
    if suffix in GLTF_FORMATS:
        _write_gltf(path, vertices, faces)
        return
    vertex_lines = "\n".join("%.17g %.17g %.17g" % tuple(v) for v in vertices)
    with atomic_output(path) as out:
        if suffix == ".off":
            out.write("OFF\n%d %d 0\n" % (len(vertices), len(faces)))
            out.write(vertex_lines + "\n")
            out.write("\n".join("3 %d %d %d" % tuple(f) for f in faces) + "\n")
        elif suffix == ".obj":
            out.write("# written by sphere_nlp\n")
            if material is not None:
                out.write("mtllib %s\n" % material)
            out.write("".join("v " + line + "\n" for line in vertex_lines.split("\n")))
            if material is not None:
                out.write("usemtl %s\n" % MATERIAL_NAME)
            if corner_uv is None:
                out.write("\n".join("f %d %d %d" % tuple(f + 1) for f in faces) + "\n")
            else:
                _write_obj_uv(out, faces, corner_uv)
        else:
            out.write("ply\nformat ascii 1.0\ncomment written by sphere_nlp\n"
                      "element vertex %d\nproperty double x\nproperty double y\nproperty double z\n"
                      "element face %d\nproperty list uchar int vertex_indices\nend_header\n"
                      % (len(vertices), len(faces)))
            out.write(vertex_lines + "\n")
            out.write("\n".join("3 %d %d %d" % tuple(f) for f in faces) + "\n")


MATERIAL_NAME = "sphere_nlp_texture"


def _write_gltf(path, vertices, faces):
    """A binary glTF (.glb) or a glTF with its buffer embedded (.gltf, one file), through trimesh:
    positions as 32-bit floats, the faces in their order."""
    import trimesh
    from trimesh.exchange.gltf import export_glb, export_gltf

    scene = trimesh.Scene(trimesh.Trimesh(vertices, faces, process=False))
    if Path(path).suffix.lower() == ".glb":
        data = export_glb(scene, include_normals=False)
    else:
        data = export_gltf(scene, include_normals=False, embed_buffers=True)["model.gltf"]
    with atomic_output(path, "wb") as out:
        out.write(data)


def write_material(path, texture):
    """Write an MTL file whose one material shows the image ``texture`` (a path relative to the MTL)
    unlit, as OBJ viewers expect: white diffuse colour times the texture, no specular highlight."""
    with atomic_output(path) as out:
        out.write("# written by sphere_nlp\nnewmtl %s\nKa 1 1 1\nKd 1 1 1\nKs 0 0 0\nillum 1\n"
                  "map_Kd %s\n" % (MATERIAL_NAME, texture))


def write_image(path, rgb):
    """Write an (h, w, 3) uint8 image as PNG, atomically."""
    from PIL import Image                      # Pillow comes with matplotlib

    with atomic_output(path, "wb") as out:
        Image.fromarray(np.asarray(rgb, np.uint8), "RGB").save(out, format="PNG")


def _write_obj_uv(out, faces, corner_uv):
    """``vt`` lines and ``f v/vt`` faces; corners with the same (u, v) share one ``vt``."""
    # Exact duplicates (a vertex's corners away from the seam and the poles) collapse into one vt;
    # 9 significant digits are far finer than any texture's texels.
    flat = corner_uv.reshape(-1, 2)
    unique_uv, first, vt_index = np.unique(flat, axis=0, return_index=True, return_inverse=True)
    # Number the vt lines in order of first use, so a file reads in face order.
    order = np.argsort(first)
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    unique_uv = unique_uv[order]
    vt_index = rank[vt_index.reshape(-1)].reshape(-1, 3)
    out.write("".join("vt %.9g %.9g\n" % tuple(uv) for uv in unique_uv))
    corners = np.stack([faces + 1, vt_index + 1], axis=-1).reshape(len(faces), 6)
    out.write("".join("f %d/%d %d/%d %d/%d\n" % tuple(row) for row in corners))


def write_json(path, data):
    """Write a JSON document atomically."""
    with atomic_output(path) as out:
        json.dump(data, out, indent=2)
        out.write("\n")


def write_npz(path, **arrays):
    """Write a .npz archive atomically."""
    with atomic_output(path, "wb") as out:
        np.savez(out, **arrays)
