"""Prepare an input mesh: check it, repair what does not change the surface, and say what was done.

:func:`prepare_mesh` is the single entry point the API uses between reading a mesh and building its
targets. In order, it

1. rejects malformed arrays: wrong shapes, non-integer or out-of-range face indices, faces that repeat
   a vertex index, non-finite coordinates (each with its own :class:`~sphere_nlp.errors.MeshInputError`);
2. normalises coordinates (centre of the bounding box at the origin, largest half-extent 1), so that
   extreme scales and offsets neither overflow nor underflow the 3D angle computations (the targets are
   angles and area ratios, which do not change);
3. drops vertices that no face uses;
4. only if the mesh as given is not a closed manifold surface, merges vertices that coincide to within
   ``1e-12`` of the bounding-box diagonal (STL triangle soups, seams duplicated for texture
   coordinates). A mesh that is already valid is never welded, so two distinct vertices that happen to
   touch in space stay distinct;
5. re-orients inconsistently oriented faces and checks the topology and the face shapes
   (:func:`~sphere_nlp.connectivity.validate_mesh`).

Vertex numbering: the repaired mesh keeps the input's vertex order, with dropped vertices removed and
each group of merged vertices represented by its lowest-numbered member. ``vertex_map[i]`` is the
repaired vertex that input vertex ``i`` became, or -1 when it was dropped. Faces are never removed or
reordered, so face ``i`` of the output is face ``i`` of the input (possibly with its winding flipped).
Error messages name vertices by their input numbers.
"""

from dataclasses import dataclass

import numpy as np

from . import errors
from .connectivity import Connectivity, check_arrays, validate_mesh

# Vertices closer than this fraction of the bounding-box diagonal are the same point (welding).
WELD_TOLERANCE = 1e-12

# Normalisation is reported (as a repair) when the input's size or offset is this far from 1.
EXTREME_SCALE = 1e4


@dataclass(frozen=True)
class PreparedMesh:
    """A validated, repaired mesh ready for the targets and the solve (plain numpy arrays).

    Attributes
    ----------
    vertices : (n, 3) float array
        Positions of the repaired vertices, in the input's coordinates.
    normalised_vertices : (n, 3) float array
        The same, centred on the bounding box and scaled to a largest half-extent of 1.
    faces : (t, 3) int array
        The input's faces in the repaired numbering, consistently oriented.
    connectivity : Connectivity
    vertex_map : (n_input,) int array
        Repaired vertex of each input vertex, -1 if dropped.
    repairs : list of str
        One line per repair made.
    centre : (3,) float array
        Centre of the bounding box, input coordinates.
    scale : float
        Largest half-extent of the bounding box, input units.
    """

    vertices: np.ndarray
    normalised_vertices: np.ndarray
    faces: np.ndarray
    connectivity: Connectivity
    vertex_map: np.ndarray
    repairs: list
    centre: np.ndarray
    scale: float


# Defects that merging duplicate vertices can cure: a soup is open everywhere and falls apart into
# one component per face; a seam is a boundary.
_WELDABLE = (errors.OpenBoundaryError, errors.ComponentsError, errors.NonManifoldEdgeError,
             errors.NonManifoldVertexError, errors.GenusError, errors.OrientationError)


def normalise(vertices, used):
    """Centre the bounding box of the used vertices at 0 and scale its largest half-extent to 1.

    A power-of-two prescale (exact in floating point) first brings the coordinates near 1, so that
    neither the extent nor the differences overflow for coordinates near 1e308.

    Returns
    -------
    normalised : (n, 3) float array
    centre : (3,) float array
    scale : float
        ``vertices ≈ centre + scale * normalised`` (in input units; may be inf for a mesh whose
        extent exceeds the float range, which normalisation still handles).

    Raises
    ------
    DegenerateFaceError
        All used vertices are at the same point.
    """
    largest = np.abs(vertices[used]).max()
    exponent = np.frexp(largest)[1] if largest > 0 else 0
    prescaled = np.ldexp(vertices, -exponent)             # |.| <= 1 on the used vertices, exactly
    lo, hi = prescaled[used].min(axis=0), prescaled[used].max(axis=0)
    centre = (lo + hi) / 2
    half = ((hi - lo) / 2).max()
    if not half > 0:
        raise errors.DegenerateFaceError("all %d vertices used by faces are at the same point"
                                         % used.sum())
    with np.errstate(over="ignore"):
        return ((prescaled - centre) / half, np.ldexp(centre, exponent), float(np.ldexp(half, exponent)))


def weld_representatives(points, tolerance):
    """For each point, the lowest index of the points within ``tolerance`` of it (transitively).

    Parameters
    ----------
    points : (n, 3) float array
    tolerance : float
        Absolute distance.

    Returns
    -------
    (n,) int array

    Examples
    --------
    >>> weld_representatives(np.array([[0., 0, 0], [1, 0, 0], [0, 0, 1e-15]]), 1e-12).tolist()
    [0, 1, 0]
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    n = len(points)
    pairs = cKDTree(points).query_pairs(tolerance, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    lowest = np.full(label.max() + 1, n)
    np.minimum.at(lowest, label, np.arange(n))
    return lowest[label]


def _compact(representative, faces, n_input):
    """Renumber the vertices that faces use, in input order; return (kept input indices, faces, map)."""
    faces = representative[faces]
    kept = np.unique(faces)
    new_index = np.full(n_input, -1)
    new_index[kept] = np.arange(len(kept))
    vertex_map = np.where(new_index[representative] >= 0, new_index[representative], -1)
    return kept, new_index[faces], vertex_map


def prepare_mesh(vertices, faces, weld_tolerance=WELD_TOLERANCE):
    """Check, repair and validate an input mesh (see the module docstring for the steps).

    Parameters
    ----------
    vertices : (n, 3) array
    faces : (t, 3) int array
    weld_tolerance : float
        Merge distance as a fraction of the bounding-box diagonal.

    Returns
    -------
    PreparedMesh

    Raises
    ------
    MeshInputError
        A subclass naming the defect.

    Examples
    --------
    >>> from sphere_nlp.shapes import octahedron
    >>> V, F = octahedron()
    >>> soup = V[F].reshape(-1, 3)                  # every face with its own three vertices
    >>> mesh = prepare_mesh(soup, np.arange(24).reshape(8, 3))
    >>> len(mesh.vertices), mesh.vertex_map[:6].tolist()
    (6, [0, 1, 2, 1, 3, 2])
    >>> mesh.repairs
    ['merged 18 duplicate vertex(es) into 6 (coincident within 1e-12 of the bounding-box diagonal)']
    """
    vertices, faces = check_arrays(vertices, faces)
    n_input = len(vertices)
    used = np.zeros(n_input, bool)
    used[faces.ravel()] = True
    normalised, centre, scale = normalise(vertices, used)
    repairs = []
    if scale > EXTREME_SCALE or scale < 1 / EXTREME_SCALE or np.abs(centre).max() > EXTREME_SCALE * scale:
        repairs.append("normalised coordinates (bounding-box centre %s, half-extent %.3g) before computing "
                       "the targets" % (np.array2string(centre, precision=3), scale))

    identity = np.arange(n_input)
    kept, compact_faces, vertex_map = _compact(identity, faces, n_input)
    try:
        _, oriented, connectivity, more = validate_mesh(normalised[kept], compact_faces, vertex_names=kept)
    except _WELDABLE as unwelded_error:
        diagonal = np.linalg.norm(np.ptp(normalised[used], axis=0))
        representative = identity.copy()
        representative[used] = np.flatnonzero(used)[
            weld_representatives(normalised[used], weld_tolerance * diagonal)]
        n_merged = int((representative[used] != np.flatnonzero(used)).sum())
        if n_merged == 0:
            raise unwelded_error
        welded = representative[faces]
        collapsed = (welded[:, 0] == welded[:, 1]) | (welded[:, 1] == welded[:, 2]) | (
            welded[:, 2] == welded[:, 0])
        if collapsed.any():
            i = int(np.flatnonzero(collapsed)[0])
            raise errors.DegenerateFaceError("%d face(s) have corners at the same position (e.g. face %d = "
                                             "%s, whose vertices coincide within %g of the bounding-box "
                                             "diagonal)" % (collapsed.sum(), i, faces[i].tolist(),
                                                            weld_tolerance)) from None
        kept, compact_faces, vertex_map = _compact(representative, faces, n_input)
        repairs.append("merged %d duplicate vertex(es) into %d (coincident within %g of the bounding-box "
                       "diagonal)" % (n_merged, len(np.unique(representative[used])), weld_tolerance))
        _, oriented, connectivity, more = validate_mesh(normalised[kept], compact_faces, vertex_names=kept)
    unused = np.flatnonzero(~used)
    if len(unused):
        repairs.append("dropped %d unreferenced vertex(es) (e.g. vertex %d)" % (len(unused), unused[0]))
    repairs += more
    return PreparedMesh(vertices=vertices[kept], normalised_vertices=normalised[kept], faces=oriented,
                        connectivity=connectivity, vertex_map=vertex_map, repairs=repairs, centre=centre,
                        scale=scale)
