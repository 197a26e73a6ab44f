"""Validated connectivity: check that a face list is a closed genus-0 surface, build the paper's tables.

Conventions used everywhere in sphere_nlp:

* ``faces[i, j]`` is the vertex at corner ``j`` of triangle ``i``; the *flat corner index* is
  ``3 * i + j``, so ``angles.ravel()[3 * i + j]`` is the angle at that corner.
* The edge *opposite* corner ``j`` joins ``faces[i, (j + 1) % 3]`` and ``faces[i, (j + 2) % 3]``.
* Each edge ``k`` has two incident triangles ``edge_faces[k] = (I1, I2)`` and the local indices of the
  corners opposite it in them, ``edge_opposite_corners[k] = (J1, J2)`` (the paper's I1, I2, J1, J2).
"""

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from . import errors


@dataclass(frozen=True)
class Connectivity:
    """Tables of a closed, oriented, genus-0 triangle mesh (all plain numpy arrays).

    Attributes
    ----------
    faces : (t, 3) int array
        Triangles, consistently oriented.
    n_vertices : int
    edges : (m, 2) int array
        Each undirected edge once, as (smaller, larger) vertex index.
    edge_faces : (m, 2) int array
        The two triangles I1, I2 sharing each edge.
    edge_opposite_corners : (m, 2) int array
        Local corner index (0..2) opposite the edge in I1 and in I2.
    vertex_degree : (n,) int array
        Number of corners (= triangles = edges) at each vertex.

    Derived data that costs seconds on large meshes is computed once and kept (``vertex_order``).
    """

    faces: np.ndarray
    n_vertices: int
    edges: np.ndarray
    edge_faces: np.ndarray
    edge_opposite_corners: np.ndarray
    vertex_degree: np.ndarray

    def vertex_order(self):
        """METIS nested-dissection order of the vertices along the edges (new -> old index),
        computed at the first call: the fill-reducing order that the start's and the unfold's sparse
        solves on large meshes restrict to their unknowns (4 s of METIS at 692k vertices, once)."""
        if "_vertex_order" not in self.__dict__:
            from .sparse_lu import nested_dissection
            graph = vertex_graph(self.edges, self.n_vertices)
            self.__dict__["_vertex_order"] = nested_dissection(graph)     # frozen: set once, here
        return self.__dict__["_vertex_order"]

    @property
    def n_faces(self):
        return len(self.faces)

    @property
    def n_edges(self):
        return len(self.edges)

    def edge_corner_indices(self):
        """Flat corner indices ``3 * I + J`` opposite each edge, shape (m, 2)."""
        return 3 * self.edge_faces + self.edge_opposite_corners

    def vertex_corner_matrix(self):
        """Sparse (n, 3t) 0/1 matrix summing corner values around each vertex (constraint (7))."""
        t = self.n_faces
        return sp.csr_matrix((np.ones(3 * t), (self.faces.ravel(), np.arange(3 * t))),
                             shape=(self.n_vertices, 3 * t))


def vertex_graph(cells, n_vertices):
    """The mesh graph as an (n, n) sparse matrix: a nonzero for each pair of vertices that share an
    edge of ``cells`` (edges (m, 2) or triangles (t, 3), of the whole mesh or a part), both ways.

    The pattern that fill-reducing orders are computed on (nested dissection, reverse Cuthill-McKee).
    """
    cells = np.asarray(cells)
    if cells.shape[1] == 2:
        a, b = cells[:, 0], cells[:, 1]
    else:
        a, b = cells.ravel(), np.roll(cells, -1, axis=1).ravel()
    return sp.csr_matrix((np.ones(2 * len(a)), (np.r_[a, b], np.r_[b, a])), shape=(n_vertices, n_vertices))


def _half_edges(faces):
    """Directed edge opposite each corner, shape (t, 3, 2): (faces[i, j+1], faces[i, j+2])."""
    return np.stack([np.roll(faces, -1, axis=1), np.roll(faces, -2, axis=1)], axis=2)


def build_connectivity(faces, n_vertices, vertex_names=None):
    """Check the topology of a face list and build the paper's connectivity tables.

    Every vertex index ``0 .. n_vertices - 1`` must be used. Faces that are oriented inconsistently
    with their neighbours are not accepted here; see :func:`orient_consistently`.

    One function of about 75 lines on purpose: each check (indices, edges, orientation, vertex fans,
    components, genus) is a few lines that build the table the next one needs, in the order the
    errors are reported, so that the first defect found is the one named.

    Parameters
    ----------
    faces : (t, 3) int array
    n_vertices : int
    vertex_names : (n_vertices,) int array, optional
        The number to print for each vertex in error messages (the user's numbering, when vertices
        were merged or dropped before this check). Default: the index itself.

    Returns
    -------
    Connectivity

    Raises
    ------
    FaceIndexError, OpenBoundaryError, NonManifoldEdgeError, OrientationError,
    NonManifoldVertexError, ComponentsError, GenusError

    Examples
    --------
    >>> from sphere_nlp.shapes import octahedron
    >>> V, F = octahedron()
    >>> c = build_connectivity(F, len(V))
    >>> c.n_edges, c.vertex_degree.tolist()
    (12, [4, 4, 4, 4, 4, 4])
    """
    faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise errors.FaceIndexError("faces must be a non-empty (t, 3) array of triangles, got shape %s"
                                    % (faces.shape,))
    faces = faces.astype(np.int64)
    t = len(faces)
    names = np.arange(n_vertices) if vertex_names is None else np.asarray(vertex_names)

    def pair(edge):
        return "%d-%d" % (names[edge[0]], names[edge[1]])

    if faces.min() < 0 or faces.max() >= n_vertices:
        bad = int(np.flatnonzero((faces < 0).any(1) | (faces >= n_vertices).any(1))[0])
        raise errors.FaceIndexError("face %d refers to a vertex index outside 0..%d" % (bad, n_vertices - 1))
    repeated = (faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 2] == faces[:, 0])
    if repeated.any():
        raise errors.FaceIndexError("%d face(s) repeat a vertex (e.g. face %d): degenerate triangles"
                                    % (repeated.sum(), np.flatnonzero(repeated)[0]))
    used = np.zeros(n_vertices, bool)
    used[faces.ravel()] = True
    unused = np.flatnonzero(~used)
    if len(unused):
        raise errors.FaceIndexError("%d vertex(es) are not used by any face (e.g. vertex %d)"
                                    % (len(unused), names[unused[0]]))

    half = _half_edges(faces).reshape(-1, 2)           # row 3*i+j: edge opposite corner (i, j)
    edges, inverse, counts = _unique_edges(half, n_vertices)
    if (counts == 1).any():
        bad = edges[counts == 1]
        raise errors.OpenBoundaryError("mesh has %d boundary edge(s) (e.g. %s): it must be closed"
                                       % (len(bad), pair(bad[0])))
    if (counts > 2).any():
        bad = edges[counts > 2]
        raise errors.NonManifoldEdgeError("mesh has %d non-manifold edge(s) shared by 3 or more faces "
                                          "(e.g. %s)" % (len(bad), pair(bad[0])))
    m = len(edges)
    order = np.argsort(inverse, kind="stable")          # the two corners of each edge, side by side
    corners = order.reshape(m, 2)
    same_direction = (half[corners[:, 0], 0] == half[corners[:, 1], 0])
    if same_direction.any():
        raise errors.OrientationError("%d edge(s) are traversed in the same direction by both faces "
                                      "(e.g. %s): orientation is inconsistent"
                                      % (same_direction.sum(), pair(edges[same_direction][0])))
    edge_faces, edge_opposite = corners // 3, corners % 3

    # Vertex manifoldness: around each vertex, corners linked across shared edges form one fan.
    # Across edge k = (a, b), the corner at a in I1 and the corner at a in I2 are neighbours.
    links = []
    for endpoint in (0, 1):
        v = edges[:, endpoint]
        c1 = 3 * edge_faces[:, 0] + np.argmax(faces[edge_faces[:, 0]] == v[:, None], axis=1)
        c2 = 3 * edge_faces[:, 1] + np.argmax(faces[edge_faces[:, 1]] == v[:, None], axis=1)
        links.append((c1, c2))
    rows = np.concatenate([l[0] for l in links])
    cols = np.concatenate([l[1] for l in links])
    fans = sp.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(3 * t, 3 * t))
    n_fans, fan_label = connected_components(fans, directed=False)
    if n_fans != n_vertices:
        fans_per_vertex = np.bincount(faces.ravel()[np.unique(fan_label, return_index=True)[1]],
                                      minlength=n_vertices)
        bad = np.flatnonzero(fans_per_vertex > 1)
        raise errors.NonManifoldVertexError("mesh has %d non-manifold (pinched) vertex(es) where separate "
                                            "fans of faces meet (e.g. vertex %d)"
                                            % (len(bad), names[bad[0]]))

    # One component: faces linked through their shared edges. Checked after the fans, so that two
    # surfaces touching at a single vertex are reported as the pinched vertex they share.
    adjacency = sp.coo_matrix((np.ones(m), (edge_faces[:, 0], edge_faces[:, 1])), shape=(t, t))
    n_comp, face_component = connected_components(adjacency, directed=False)
    if n_comp > 1:
        sizes = np.sort(np.bincount(face_component))[::-1]
        shown = ", ".join(str(k) for k in sizes[:5]) + (", ..." if n_comp > 5 else "")
        raise errors.ComponentsError("mesh has %d connected components (faces per component: %s): it "
                                     "must have exactly one" % (n_comp, shown))

    chi = n_vertices - m + t
    if chi != 2:
        genus = (2 - chi) // 2
        raise errors.GenusError("mesh has genus %d (V - E + F = %d): only genus 0 (sphere-like) surfaces "
                                "can be mapped to the sphere" % (genus, chi))
    return Connectivity(faces=faces, n_vertices=int(n_vertices), edges=edges, edge_faces=edge_faces,
                        edge_opposite_corners=edge_opposite,
                        vertex_degree=np.bincount(faces.ravel(), minlength=n_vertices))


def _unique_edges(half, n_vertices):
    """The undirected edges (m, 2) of half-edges (k, 2) sorted by (low, high) vertex, the edge of each
    half-edge (k,), and how many half-edges each edge has (m,).

    Each edge is one int64 key low * n + high: sorting those is several times faster than numpy's
    unique over rows, and gives the same order.
    """
    key = np.sort(half, axis=1)
    keys, inverse, counts = np.unique(key[:, 0] * np.int64(n_vertices) + key[:, 1],
                                      return_inverse=True, return_counts=True)
    return np.stack(np.divmod(keys, np.int64(n_vertices)), axis=1), inverse.ravel(), counts


def _edge_corner_pairs(faces):
    """Directed half-edges (3t, 2) and, for each undirected edge, its two flat corner indices (m, 2)."""
    half = _half_edges(faces).reshape(-1, 2)
    _, inverse, _ = _unique_edges(half, int(half.max()) + 1)
    return half, np.argsort(inverse, kind="stable").reshape(-1, 2)


def orient_consistently(faces):
    """Flip faces so that every edge is traversed once in each direction.

    Orientation is propagated along a breadth-first spanning tree of each component; the winding
    of the majority of its faces is kept, so as few faces as possible are flipped. Edges must already
    be manifold (two faces each).

    Returns
    -------
    faces : (t, 3) int array
    n_flipped : int

    Raises
    ------
    OrientationError
        For a non-orientable surface.
    """
    from scipy.sparse.csgraph import breadth_first_order

    faces = np.asarray(faces, dtype=np.int64).copy()
    t = len(faces)
    half, corners = _edge_corner_pairs(faces)
    f1, f2 = corners[:, 0] // 3, corners[:, 1] // 3
    disagree = half[corners[:, 0], 0] == half[corners[:, 1], 0]
    # Stored as 1 (agree) / 2 (disagree) so that both are explicit entries of the sparse matrix.
    relation = sp.coo_matrix((disagree + 1.0, (f1, f2)), shape=(t, t)).tocsr()
    relation = relation + relation.T
    parent = np.full(t, -1)
    component = np.full(t, -1)
    for start in range(t):
        if component[start] < 0:
            order, pred = breadth_first_order(relation, start, directed=False)
            component[order] = start
            parent[order[1:]] = pred[order[1:]]
    child = np.flatnonzero(parent >= 0)
    parity = np.zeros(t, bool)
    parity[child] = np.asarray(relation[child, parent[child]]).ravel() == 2
    # Pointer doubling: parity to the root = XOR of the parities along the tree path.
    ancestor = parent.copy()
    has = ancestor >= 0
    while has.any():
        parity[has] = parity[has] ^ parity[ancestor[has]]   # right side uses the old values
        ancestor[has] = ancestor[ancestor[has]]
        has = ancestor >= 0
    # Keep the winding of the majority of each component: flip the fewest faces.
    flipped_share = np.bincount(component, weights=parity, minlength=t) / np.maximum(
        np.bincount(component, minlength=t), 1)
    parity ^= flipped_share[component] > 0.5
    faces[parity] = faces[parity][:, ::-1]
    half, corners = _edge_corner_pairs(faces)
    if (half[corners[:, 0], 0] == half[corners[:, 1], 0]).any():
        raise errors.OrientationError("mesh is not orientable (for example a Moebius band or Klein bottle)")
    return faces, int(parity.sum())


def check_arrays(vertices, faces):
    """Reject malformed vertex and face arrays; return them as float64 and int64.

    Raises
    ------
    UnreadableMeshError
        ``vertices`` is not a non-empty (n, 3) array.
    FaceIndexError
        ``faces`` is not a non-empty (t, 3) array of integers in 0..n-1, or a face repeats an index.
    NonFiniteCoordinatesError
        A coordinate is NaN or infinite.
    """
    try:
        vertices = np.asarray(vertices, dtype=float)
    except (TypeError, ValueError):
        raise errors.UnreadableMeshError("vertices must be an (n, 3) array of numbers") from None
    if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) == 0:
        raise errors.UnreadableMeshError("vertices must be a non-empty (n, 3) array, got shape %s"
                                         % (vertices.shape,))
    try:
        faces = np.asarray(faces)
    except ValueError:
        raise errors.FaceIndexError("faces must be a (t, 3) array of triangles (ragged input?)") from None
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise errors.FaceIndexError("faces must be a non-empty (t, 3) array of triangles, got shape %s"
                                    % (faces.shape,))
    if not np.issubdtype(faces.dtype, np.integer):
        if not (np.issubdtype(faces.dtype, np.number) and np.isfinite(faces).all()
                and np.array_equal(faces, np.round(faces))):
            raise errors.FaceIndexError("face indices must be integers")
    faces = faces.astype(np.int64)
    n = len(vertices)
    outside = (faces < 0) | (faces >= n)
    if outside.any():
        i, j = np.argwhere(outside)[0]
        raise errors.FaceIndexError("%d face(s) refer to vertices that do not exist (e.g. face %d refers to "
                                    "vertex %d; there are %d vertices, 0..%d)"
                                    % (outside.any(axis=1).sum(), i, faces[i, j], n, n - 1))
    repeated = (faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 2] == faces[:, 0])
    if repeated.any():
        i = int(np.flatnonzero(repeated)[0])
        raise errors.FaceIndexError("%d face(s) repeat a vertex index (e.g. face %d = %s): degenerate "
                                    "triangles" % (repeated.sum(), i, faces[i].tolist()))
    bad = ~np.isfinite(vertices).all(axis=1)
    if bad.any():
        first = np.flatnonzero(bad)[0]
        raise errors.NonFiniteCoordinatesError("%d vertex(es) have non-finite coordinates (e.g. vertex %d = "
                                               "%s)" % (bad.sum(), first, vertices[first].tolist()))
    return vertices, faces


# A face whose smallest 3D corner angle is below this (radians) counts as degenerate: its corners are
# collinear to working precision and its target angles and area mean nothing.
DEGENERATE_ANGLE = 1e-10


def validate_mesh(vertices, faces, vertex_names=None):
    """Check a mesh for use as input and build its connectivity.

    Repairs that do not change the surface are applied and listed: faces oriented inconsistently with
    their neighbours are flipped to agree with the majority. Everything else that is wrong raises a
    :class:`~sphere_nlp.errors.MeshInputError` subclass with a one-line message.

    Parameters
    ----------
    vertices : (n, 3) array
    faces : (t, 3) int array
    vertex_names : (n,) int array, optional
        Vertex numbers to use in error messages (see :func:`build_connectivity`).

    Returns
    -------
    vertices : (n, 3) float array
    faces : (t, 3) int array
        Possibly with some faces flipped.
    connectivity : Connectivity
    repairs : list of str
        One human-readable line per repair made.

    Examples
    --------
    >>> from sphere_nlp.shapes import cylinder
    >>> V, F = cylinder()
    >>> F[0] = F[0, ::-1]
    >>> V, F, conn, repairs = validate_mesh(V, F)
    >>> repairs
    ['flipped 1 face(s) to make the orientation consistent']
    """
    from .geometry import corner_angles

    vertices, faces = check_arrays(vertices, faces)
    repairs = []
    try:
        connectivity = build_connectivity(faces, len(vertices), vertex_names)
    except errors.OrientationError:
        faces, flipped = orient_consistently(faces)
        repairs.append("flipped %d face(s) to make the orientation consistent" % flipped)
        connectivity = build_connectivity(faces, len(vertices), vertex_names)
    min_angle = corner_angles(vertices, faces).min(axis=1)
    degenerate = ~(min_angle > DEGENERATE_ANGLE)
    if degenerate.any():
        first = int(np.flatnonzero(degenerate)[0])
        raise errors.DegenerateFaceError("mesh has %d degenerate (zero-area) face(s) (e.g. face %d, smallest "
                                         "angle %.3g rad, below %g): remove or fix them"
                                         % (degenerate.sum(), first, min_angle[first], DEGENERATE_ANGLE))
    return vertices, faces, connectivity, repairs
