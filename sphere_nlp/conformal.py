"""The linear spherical conformal map of Choi, Lam & Lui (2015, "FLASH"), and its finite elements.

The solver's default start (:func:`sphere_nlp.starts.starting_positions`) and a baseline of
:mod:`sphere_nlp.baselines`. Plain numpy and scipy.sparse.
"""

import numpy as np
import scipy.sparse as sp

from . import sparse_lu
from .connectivity import vertex_graph

from .geometry import cross, scatter_to_vertices, triangle_areas, triangles_with_angles


# --- shared finite-element pieces -------------------------------------------------------------------

def cotan_laplacian(vertices, faces):
    """Cotangent Laplacian (stiffness matrix) of a triangle mesh, (n, n) sparse, positive semidefinite.

    ``K[i, j] = -(cot alpha_ij + cot beta_ij) / 2`` for an edge ij (alpha, beta the angles opposite
    it), rows summing to zero; ``x @ K @ x`` is the Dirichlet energy of the piecewise-linear function x.

    Examples
    --------
    >>> from sphere_nlp.shapes import octahedron
    >>> V, F = octahedron()
    >>> K = cotan_laplacian(V, F)
    >>> bool(abs(K.sum(axis=1)).max() < 1e-15), bool(np.isclose(K[0, 2], -1 / np.sqrt(3)))  # cot 60 deg
    (True, True)
    """
    vertices = np.asarray(vertices, dtype=float)
    faces = np.asarray(faces, dtype=np.int64)
    return _cotan_laplacian_of_corners(faces, vertices[faces], len(vertices))


def _cotan_laplacian_of_corners(faces, corners, n):
    """:func:`cotan_laplacian` from each face's own corner positions (t, 3, 3), which need not be
    shared between faces (the cotangents depend on each triangle's shape only)."""
    to_next = np.roll(corners, -1, axis=1) - corners
    to_prev = np.roll(corners, 1, axis=1) - corners
    # cot of the angle at corner k = dot / |cross|; it weighs the edge opposite that corner.
    cot = (np.einsum("tjk,tjk->tj", to_next, to_prev)
           / np.linalg.norm(cross(to_next, to_prev), axis=2))
    return _assemble_edge_weights(faces, 0.5 * cot, n)


def _assemble_edge_weights(faces, corner_weight, n):
    """Laplacian from a weight per corner, put on the edge opposite that corner (no face loops)."""
    i = np.roll(faces, -1, axis=1).ravel()           # the edge opposite corner k: (k+1, k+2)
    j = np.roll(faces, -2, axis=1).ravel()
    w = corner_weight.ravel()
    W = sp.coo_matrix((np.r_[w, w], (np.r_[i, j], np.r_[j, i])), shape=(n, n)).tocsr()
    return (sp.diags(np.asarray(W.sum(axis=1)).ravel()) - W).tocsr()


def lumped_mass(vertices, faces):
    """Barycentric lumped mass matrix: a third of the area of each incident triangle, (n, n) diagonal."""
    return sp.diags(scatter_to_vertices(faces, triangle_areas(vertices, faces) / 3, len(vertices)))


# FLASH's two solves are ordered by the mesh's nested dissection only from this many vertices, not
# from sparse_lu.NESTED_DISSECTION_UNKNOWNS like the other Laplacian solves: the order changes the
# start by rounding, which where limbs collapse past double precision changes the angle solve's path
# (thin:27k equal-angles: 55 iterations to 1616.6 instead of 39 to 1478.9), for 0.3 s at 50k
# vertices; at 173k it saves 1.6 s (docs/tuning.md, "Large meshes").
NESTED_DISSECTION_UNKNOWNS = 100_000


def _dirichlet_solve(K, values, fixed, vertex_order=None):
    """Solve K x = 0 on the free vertices with x = values on ``fixed``; values is (n, k), returns (n, k).

    ``vertex_order``: a nested-dissection order of all vertices (new -> old), restricted to the free
    ones (:func:`sphere_nlp.sparse_lu.restricted_order`)."""
    n = K.shape[0]
    free = np.ones(n, bool)
    free[fixed] = False
    x = np.array(values, dtype=float)
    K = K.tocsr()
    rhs = -(K[free][:, ~free] @ x[~free])
    ordering = sparse_lu.restricted_order(vertex_order, free, minimum=NESTED_DISSECTION_UNKNOWNS)
    x[free] = sparse_lu.solve(K[free][:, free], np.asarray(rhs, dtype=float), ordering=ordering)
    return x


def _inversion(z):
    """z / |z|^2 for plane points (n, 2): the south-pole stereographic coordinates of the points whose
    north-pole ones are z, computed without the cancellation in 1 + S_z near the south pole
    (inf for z = 0, the south pole itself)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return z / np.einsum("ij,ij->i", z, z)[:, None]


def _inverse_stereographic(z, from_pole=1.0):
    """Unit-sphere points from plane points (n, 2).

    ``from_pole=1``: projection from the north pole (the plane's infinity is (0, 0, 1));
    ``from_pole=-1``: from the south pole.
    """
    r2 = np.einsum("ij,ij->i", z, z)
    return np.c_[2 * z, from_pole * (r2 - 1)] / (1 + r2)[:, None]


# --- Choi, Lam & Lui (2015) ---------------------------------------------------------------------------

def _most_regular_face(corners):
    """The face whose edge lengths are closest to a third of its perimeter each (FLASH's big triangle)."""
    lengths = np.linalg.norm(np.roll(corners, -1, axis=1) - corners, axis=2)
    regularity = np.abs(lengths / lengths.sum(axis=1, keepdims=True) - 1 / 3).sum(axis=1)
    return int(np.argmin(regularity))


def beltrami_coefficient(plane, faces, vertices):
    """Beltrami coefficient of the map from plane positions (n, 2) to the 3D surface, per face, (t,) complex.

    Per face, the surface's first fundamental form E, F, G in the plane's coordinates gives
    mu = (E - G + 2iF) / (E + G + 2 sqrt(EG - F^2)); mu = 0 where the map is conformal.
    """
    return _beltrami_of_corners(plane, faces, np.asarray(vertices, dtype=float)[faces])


def _beltrami_of_corners(plane, faces, corners):
    """:func:`beltrami_coefficient` with each face's own corner positions (t, 3, 3): the faces need
    not share vertices, and the coefficient does not change with a face's size or placement."""
    Q = plane[faces]                                   # (t, 3, 2)
    e1, e2 = Q[:, 1] - Q[:, 0], Q[:, 2] - Q[:, 0]
    signed_area2 = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    X = corners
    d1, d2 = X[:, 1] - X[:, 0], X[:, 2] - X[:, 0]
    # Gradient of a linear function on the face from its differences along e1, e2 (Cramer's rule).
    du = (d1 * e2[:, 1, None] - d2 * e1[:, 1, None]) / signed_area2[:, None]
    dv = (d2 * e1[:, 0, None] - d1 * e2[:, 0, None]) / signed_area2[:, None]
    E = np.einsum("ij,ij->i", du, du)
    G = np.einsum("ij,ij->i", dv, dv)
    F = np.einsum("ij,ij->i", du, dv)
    return (E - G + 2j * F) / (E + G + 2 * np.sqrt(np.maximum(E * G - F ** 2, 0)))


def linear_beltrami_solver(plane, faces, mu, fixed, targets):
    """Quasi-conformal map of the plane mesh with Beltrami coefficient ``mu``, fixed vertices pinned.

    Solves div(A grad u) = 0 for both coordinates, where the symmetric A of each face is
    [[(1 - 2 Re mu + |mu|^2), -2 Im mu], [-2 Im mu, (1 + 2 Re mu + |mu|^2)]] / (1 - |mu|^2)
    (Lui et al.'s linear Beltrami solver, as used by FLASH), discretised with linear elements.
    """
    mu = np.asarray(mu, dtype=complex)
    # |mu| -> 1 makes A singular; such faces are degenerate in the map anyway.
    size = np.abs(mu)
    mu = np.where(size > 1 - 1e-9, mu / np.maximum(size, 1e-300) * (1 - 1e-9), mu)
    denominator = 1 - np.abs(mu) ** 2
    a = (1 - 2 * mu.real + np.abs(mu) ** 2) / denominator
    b = -2 * mu.imag / denominator
    c = (1 + 2 * mu.real + np.abs(mu) ** 2) / denominator
    Q = plane[faces]
    # Rotated opposite edges: grad phi_k = rot(edge opposite k) / (2 area) for the hat function of k.
    opposite = np.roll(Q, -2, axis=1) - np.roll(Q, -1, axis=1)        # q_{k+2} - q_{k+1}
    r = np.stack([-opposite[..., 1], opposite[..., 0]], axis=2)        # (t, 3, 2)
    e1, e2 = Q[:, 1] - Q[:, 0], Q[:, 2] - Q[:, 0]
    area = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    Ar = np.stack([a[:, None] * r[..., 0] + b[:, None] * r[..., 1],
                   b[:, None] * r[..., 0] + c[:, None] * r[..., 1]], axis=2)
    local = np.einsum("tid,tjd->tij", r, Ar) / (4 * area)[:, None, None]  # (t, 3, 3) element matrix
    rows = np.repeat(faces, 3, axis=1).ravel()
    cols = np.tile(faces, (1, 3)).ravel()
    n = len(plane)
    K = sp.coo_matrix((local.ravel(), (rows, cols)), shape=(n, n)).tocsr()
    values = np.zeros((n, 2))
    values[fixed] = targets
    return _dirichlet_solve(K, values, fixed)


def conformal_map(vertices, faces, fixed_fraction=0.1, angles=None, vertex_order=None):
    """Linear spherical conformal map of Choi, Lam & Lui (2015), "FLASH", SIAM J. Imaging Sci. 8(1).

    Two linear solves, as in the paper:

    1. **North-pole step.** Remove the most regular triangle (the "big triangle"), place it in the plane
       with its 3D shape, and solve the Laplace equation (cotangent Laplacian) for the rest of the mesh
       inside it: a discrete harmonic, hence nearly conformal, map of the punctured sphere to the plane.
       Inverse stereographic projection (from the north pole) puts the big triangle around the north
       pole. The plane is first scaled so that the big triangle and the triangle nearest the south pole
       come out about equally large (the reference implementation's "optimal big triangle size").
    2. **South-pole step.** The harmonic map is least conformal near the north pole, where the fixed big
       triangle forces it. Project stereographically from the south pole, so that this region lies near
       the origin, and solve for a map with the Beltrami coefficient mu of the map from that plane back
       to the surface while pinning the vertices nearest the south pole (a fraction
       ``fixed_fraction`` of them, at least 3), whose positions were already conformal. The
       composition has Beltrami coefficient ~0, i.e. is conformal everywhere. Inverse stereographic
       projection from the south pole gives the sphere.

    FLASH solves step 2 with the linear Beltrami solver (:func:`linear_beltrami_solver`) on mu from
    :func:`beltrami_coefficient`. Per linear element, the solver's matrix A(mu) is sqrt(det g) g^-1
    for the metric g that the face's 3D triangle pulls back to the plane, so its element matrix is the
    3D triangle's own cotangent matrix: step 2 is step 1's Laplacian with the south-pole boundary
    values (equal to 1e-13 on bunny.off). This form never divides by a plane triangle's area,
    which is zero where a thin limb's tip collapses in the plane (mu there is 0/0).

    If the solve is singular or not finite the pinned set is enlarged 5 times once, then the step
    is skipped (the reference implementation does the same). The map is not guaranteed to be
    bijective: cotangent weights can be negative on obtuse meshes.

    With ``angles`` the map is conformal to the metric those corner angles describe instead of the
    surface's: each triangle takes the planar shape of its angles
    (:func:`sphere_nlp.geometry.triangles_with_angles`). Both steps use only each triangle's shape
    (the cotangents do not change with its size), so the triangles need
    not agree on their shared edges. Given an angle mode's targets this is the linearised map the
    solve is looking for: the equal modes' 2 pi / deg targets give a map far from the surface's.

    Parameters
    ----------
    vertices : (n, 3) float array
        The surface; with ``angles``, only its number of vertices is used.
    faces : (t, 3) int array
        Closed genus-0 triangle mesh, outward (counter-clockwise) faces.
    fixed_fraction : float
        Fraction of vertices pinned near the south pole in step 2.
    angles : (t, 3) float array, optional
        Corner angles of the metric to map conformally (default: the surface's).
    vertex_order : (n,) int array, optional
        A nested-dissection order of the vertices (``Connectivity.vertex_order``), which the two
        solves restrict to their unknowns; computed here from the faces if not given (from
        :data:`NESTED_DISSECTION_UNKNOWNS` vertices; below that SuperLU orders each solve itself).

    Returns
    -------
    (n, 3) float array of unit vectors.

    Examples
    --------
    >>> from sphere_nlp.shapes import icosphere
    >>> from sphere_nlp.metrics import distortion_summary
    >>> V, F = icosphere(2)
    >>> s = distortion_summary(V * [1, 1, 1.5], conformal_map(V * [1, 1, 1.5], F), F)
    >>> s["valid"], s["qc_mean"] < 1.1
    (True, True)
    """
    vertices = np.asarray(vertices, dtype=float)
    faces = np.asarray(faces, dtype=np.int64)
    n = len(vertices)
    if vertex_order is None and n >= NESTED_DISSECTION_UNKNOWNS:
        vertex_order = sparse_lu.nested_dissection(vertex_graph(faces, n))
    corners = vertices[faces] if angles is None else triangles_with_angles(angles)
    # Step 1: harmonic map into the big triangle.
    big = _most_regular_face(corners)
    p1, p2, p3 = faces[big]
    a, b = corners[big, 1] - corners[big, 0], corners[big, 2] - corners[big, 0]
    scale = 1 / np.linalg.norm(a)
    # p1 at 0, p2 at 1, p3 where the triangle's shape puts it (counter-clockwise, so the rest comes out
    # clockwise in the plane and counter-clockwise on the sphere after the orientation-reversing projection).
    third = scale * np.array([a @ b / np.linalg.norm(a), np.linalg.norm(cross(a, b)) / np.linalg.norm(a)])
    boundary = np.zeros((n, 2))
    boundary[p2] = [1, 0]
    boundary[p3] = third
    stiffness = _cotan_laplacian_of_corners(faces, corners, n)
    z = _dirichlet_solve(stiffness, boundary, [p1, p2, p3], vertex_order)
    z -= z.mean(axis=0)
    # Scale the plane so the big triangle (around the north pole) and the triangle nearest the south
    # pole get about the same size on the sphere.
    w = _inversion(z)                                          # south-pole stereographic coordinates
    order = np.argsort(np.linalg.norm(z[faces], axis=2).sum(axis=1))
    inner = order[1] if order[0] == big else order[0]

    def mean_side(points, face):
        corners = points[faces[face]]
        return np.linalg.norm(corners - np.roll(corners, 1, axis=0), axis=1).mean()

    north_side, south_side = mean_side(z, big), mean_side(w, inner)
    if np.isfinite(south_side) and south_side > 0:
        z *= np.sqrt(north_side * south_side) / north_side
    S = _inverse_stereographic(z)

    # Step 2: the harmonic map again, in south-pole stereographic coordinates, pinned near the south pole.
    by_height = np.argsort(S[:, 2])
    plane = _inversion(z)
    Q = np.delete(plane[faces], big, axis=0)                # the big triangle is the plane's outside
    e1, e2 = Q[:, 1] - Q[:, 0], Q[:, 2] - Q[:, 0]
    with np.errstate(invalid="ignore"):
        signed_area2 = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    if not np.all(np.isfinite(signed_area2) & (signed_area2 != 0)):
        # Triangles of zero area in the plane: limbs shrunk past double precision. The
        # correction would shrink their tips further still (a body of eight legs of 20-45 radii:
        # smallest triangle 6e-30 of its share against 8e-28), below what the solve's answer can
        # be unfolded at, so the first step's map is kept, as FLASH does when its solve fails.
        return S
    count = max(round(n * fixed_fraction), 3)
    for attempt in range(2):
        fixed = by_height[:min(n, count)]
        if not np.isfinite(plane[fixed]).all():
            break                                            # a pinned vertex at the plane's infinity
        try:
            solved = _dirichlet_solve(stiffness, plane, fixed, vertex_order)
        except RuntimeError:                                # singular, or not finite
            solved = None
        if solved is not None and np.isfinite(solved).all():
            return _inverse_stereographic(solved, from_pole=-1.0)
        count *= 5
    return S
