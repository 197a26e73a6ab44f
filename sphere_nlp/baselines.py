"""Baseline spherical maps to compare sphere_nlp against.

* :func:`alexa_relaxation`: the relaxation of Alexa (2000), the method of panel (b) of the paper's Fig. 3.
* :func:`conformal_map`: the linear spherical conformal map of Choi, Lam & Lui (2015, FLASH).
* :func:`cmcf_map`: conformalized mean curvature flow (Kazhdan, Solomon & Ben-Chen 2012).
* :func:`tutte_projection`: the valid-by-construction convex embedding sphere_nlp starts from.

All of them return positions whether or not the map is valid; check them with
:func:`sphere_nlp.certify.certify`.
"""

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .certify import Certificate, certify
from .targets import triangle_areas_3d

STARTS = ("central", "normals")


@dataclass
class AlexaRelaxation:
    """Result of :func:`alexa_relaxation`.

    Attributes
    ----------
    positions : (n, 3) float array
        Vertex positions on the unit sphere, in input order.
    iterations : int
        Relaxation sweeps performed.
    converged : bool
        True when the largest vertex move of the last sweep fell below ``tol``.
    last_move : float
        Largest vertex move (Euclidean) of the last sweep.
    certificate : Certificate
        :func:`sphere_nlp.certify.certify` of ``positions``: convergence alone does not mean the map
        is valid (the relaxation can converge to a collapsed or folded configuration).
    """

    positions: np.ndarray
    iterations: int
    converged: bool
    last_move: float
    certificate: Certificate


def _edges(faces):
    """Unique undirected edges (m, 2) of a triangle mesh."""
    pairs = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return np.unique(np.sort(pairs, axis=1), axis=0)


def _start_positions(vertices, faces, start):
    """Initial sphere positions: central projection from the centroid, or the Gauss map of normals."""
    if not isinstance(start, str):
        positions = np.array(start, dtype=float)
        if positions.shape != vertices.shape:
            raise ValueError("start positions must have shape %s" % (vertices.shape,))
    elif start == "central":
        # The area-weighted surface centroid, so dense regions of the mesh do not pull the centre.
        areas = triangle_areas_3d(vertices, faces)
        centre = (areas[:, None] * vertices[faces].mean(axis=1)).sum(axis=0) / areas.sum()
        positions = vertices - centre
    elif start == "normals":
        # Area-weighted vertex normals: the Gauss map, for meshes not star-shaped about any point.
        P = vertices[faces]
        face_normals = np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])   # length = 2 * area
        positions = np.zeros_like(vertices)
        for k in range(3):
            np.add.at(positions, faces[:, k], face_normals)
    else:
        raise ValueError("start must be one of %s or an (n, 3) array" % (STARTS,))
    norms = np.linalg.norm(positions, axis=1, keepdims=True)
    if not (norms > 0).all():
        raise ValueError("a start position is at the centre; the central projection is undefined there")
    return positions / norms


def alexa_relaxation(vertices, faces, max_iter=10000, tol=1e-10, step=0.5, start="central",
                     edge_length_weights=True, recentre=True, anchors=None):
    """Spherical relaxation of Alexa (2000), "Merging polyhedral shapes with scattered features".

    Start from a map of the mesh onto the unit sphere, then repeat: move every vertex toward the
    weighted centroid of its neighbours and project it back onto the sphere, until no vertex moves
    more than ``tol``. What is implemented, and why:

    * **Start** (``start``): the central projection of the vertices from the mesh's centroid, which is
      a valid map for meshes star-shaped about it (the cylinder is); ``"normals"`` uses the Gauss map
      (area-weighted vertex normals) instead, for meshes that are not star-shaped.
    * **Edge-length weights** (``edge_length_weights``): neighbour j of vertex i gets weight
      ``|x_j - x_i|``, Alexa's measure against fold-overs: long (stretched) edges pull harder than
      short ones, so crowded, folded regions spread out instead of being pulled further together.
      With uniform weights the iteration is the plain "barycentric" relaxation.
    * **Damping** (``step``): ``x_i <- x_i + step (c_i - x_i)`` with c_i the weighted centroid;
      with edge-length weights the undamped (``step=1``) sweep oscillates and does not converge.
    * **Against collapse**: the energy the relaxation descends is smallest when all vertices meet in
      one point, and the plain iteration drifts there from any slightly asymmetric start. Alexa holds
      some vertices fixed; ``anchors`` does that (indices of vertices kept at their start
      positions). By default we instead subtract the vertices' mean before each projection
      (``recentre``), which removes the drift of the whole point set toward one side of the sphere
      without pinning any vertex (pinned vertices bias the result toward the start and can force
      fold-overs next to them). Anchors and re-centring are exclusive: re-centring would move anchors.
    * Sweeps are Jacobi (all vertices at once, with one sparse matrix product), not Gauss-Seidel.

    The exact constants of the 2000 paper could not be checked here; the weights, damping and
    collapse guard above follow the method as it is usually described (edge-length-weighted
    neighbour averaging with projection, fixed vertices against collapse). Convergence is not
    guaranteed and a converged result need not be valid, so the result carries its certificate.

    Parameters
    ----------
    vertices : (n, 3) float array
    faces : (t, 3) int array
        A closed genus-0 triangle mesh with outward (counter-clockwise) faces.
    max_iter : int
        Maximum number of sweeps.
    tol : float
        Convergence threshold on the largest vertex move of a sweep.
    step : float
        Damping factor in (0, 1].
    start : {"central", "normals"} or (n, 3) array
        Initial sphere positions (an array is normalised onto the sphere).
    edge_length_weights : bool
        Weight neighbours by edge length (True) or uniformly (False).
    recentre : bool
        Subtract the vertices' mean before projecting, against collapse. Ignored with ``anchors``.
    anchors : array of int, optional
        Vertices held at their start positions, Alexa's guard against collapse.

    Returns
    -------
    AlexaRelaxation

    Examples
    --------
    >>> from sphere_nlp.shapes import cylinder
    >>> V, F = cylinder()
    >>> result = alexa_relaxation(V, F)
    >>> result.converged, result.certificate.valid, result.iterations < 1000
    (True, True, True)
    """
    vertices = np.asarray(vertices, dtype=float)
    faces = np.asarray(faces, dtype=np.int64)
    if not 0 < step <= 1:
        raise ValueError("step must be in (0, 1]")
    n = len(vertices)
    i, j = _edges(faces).T
    rows, cols = np.r_[i, j], np.r_[j, i]
    free = np.ones(n, bool)
    if anchors is not None:
        free[np.asarray(anchors, dtype=np.int64)] = False
        recentre = False

    X = _start_positions(vertices, faces, start)
    move = np.inf
    iterations = 0
    while iterations < max_iter and not move < tol:
        iterations += 1
        w = np.linalg.norm(X[i] - X[j], axis=1) if edge_length_weights else np.ones(len(i))
        W = sp.csr_matrix((np.r_[w, w], (rows, cols)), shape=(n, n))
        total = np.asarray(W.sum(axis=1)).ravel()
        centroid = (W @ X) / np.where(total > 0, total, 1.0)[:, None]
        Y = X + step * (centroid - X)
        if recentre:
            Y -= Y.mean(axis=0)
        Y[~free] = X[~free]
        norms = np.linalg.norm(Y, axis=1, keepdims=True)
        if not (norms > 0).all():      # a vertex reached the centre: the projection is undefined
            break
        Y /= norms
        move = float(np.max(np.linalg.norm(Y - X, axis=1)))
        X = Y
    return AlexaRelaxation(positions=X, iterations=iterations, converged=bool(move < tol),
                           last_move=move, certificate=certify(X, faces))


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
    P = vertices[faces]
    to_next = np.roll(P, -1, axis=1) - P
    to_prev = np.roll(P, 1, axis=1) - P
    # cot of the angle at corner k = dot / |cross|; it weighs the edge opposite that corner.
    cot = (np.einsum("tjk,tjk->tj", to_next, to_prev)
           / np.linalg.norm(np.cross(to_next, to_prev), axis=2))
    return _assemble_edge_weights(faces, 0.5 * cot, len(vertices))


def _assemble_edge_weights(faces, corner_weight, n):
    """Laplacian from a weight per corner, put on the edge opposite that corner (no face loops)."""
    i = np.roll(faces, -1, axis=1).ravel()           # the edge opposite corner k: (k+1, k+2)
    j = np.roll(faces, -2, axis=1).ravel()
    w = corner_weight.ravel()
    W = sp.coo_matrix((np.r_[w, w], (np.r_[i, j], np.r_[j, i])), shape=(n, n)).tocsr()
    return (sp.diags(np.asarray(W.sum(axis=1)).ravel()) - W).tocsr()


def lumped_mass(vertices, faces):
    """Barycentric lumped mass matrix: a third of the area of each incident triangle, (n, n) diagonal."""
    areas = triangle_areas_3d(vertices, faces)
    mass = np.bincount(np.asarray(faces).ravel(), weights=np.repeat(areas / 3, 3), minlength=len(vertices))
    return sp.diags(mass)


def _dirichlet_solve(K, values, fixed):
    """Solve K x = 0 on the free vertices with x = values on ``fixed``; values is (n, k), returns (n, k)."""
    n = K.shape[0]
    free = np.ones(n, bool)
    free[fixed] = False
    x = np.array(values, dtype=float)
    K = K.tocsr()
    rhs = -(K[free][:, ~free] @ x[~free])
    x[free] = spla.splu(K[free][:, free].tocsc()).solve(np.asarray(rhs, dtype=float))
    return x


def _inverse_stereographic(z, from_pole=1.0):
    """Unit-sphere points from plane points (n, 2).

    ``from_pole=1``: projection from the north pole (the plane's infinity is (0, 0, 1));
    ``from_pole=-1``: from the south pole.
    """
    r2 = np.einsum("ij,ij->i", z, z)
    return np.c_[2 * z, from_pole * (r2 - 1)] / (1 + r2)[:, None]


# --- Choi, Lam & Lui (2015) ---------------------------------------------------------------------------

def _most_regular_face(vertices, faces):
    """The face whose edge lengths are closest to a third of its perimeter each (FLASH's big triangle)."""
    P = vertices[faces]
    lengths = np.linalg.norm(np.roll(P, -1, axis=1) - P, axis=2)
    regularity = np.abs(lengths / lengths.sum(axis=1, keepdims=True) - 1 / 3).sum(axis=1)
    return int(np.argmin(regularity))


def beltrami_coefficient(plane, faces, vertices):
    """Beltrami coefficient of the map from plane positions (n, 2) to the 3D surface, per face, (t,) complex.

    Per face, the surface's first fundamental form E, F, G in the plane's coordinates gives
    mu = (E - G + 2iF) / (E + G + 2 sqrt(EG - F^2)); mu = 0 where the map is conformal.
    """
    Q = plane[faces]                                   # (t, 3, 2)
    e1, e2 = Q[:, 1] - Q[:, 0], Q[:, 2] - Q[:, 0]
    signed_area2 = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    X = vertices[faces]
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


def conformal_map(vertices, faces, fixed_fraction=0.1):
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
       the origin; compute the Beltrami coefficient mu of the map from that plane back to the surface;
       then solve the linear Beltrami solver for a map with that same mu while pinning the vertices
       nearest the south pole (a fraction ``fixed_fraction`` of them, at least 3), whose positions were
       already conformal. The composition has Beltrami coefficient ~0, i.e. is conformal everywhere.
       Inverse stereographic projection from the south pole gives the sphere.

    If the Beltrami solve produces non-finite values the pinned set is enlarged 5 times once, then the
    step is skipped (the reference implementation does the same). The map is not guaranteed to be
    bijective: cotangent weights can be negative on obtuse meshes.

    Parameters
    ----------
    vertices : (n, 3) float array
    faces : (t, 3) int array
        Closed genus-0 triangle mesh, outward (counter-clockwise) faces.
    fixed_fraction : float
        Fraction of vertices pinned near the south pole in step 2.

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
    # Step 1: harmonic map into the big triangle.
    big = _most_regular_face(vertices, faces)
    p1, p2, p3 = faces[big]
    a, b = vertices[p2] - vertices[p1], vertices[p3] - vertices[p1]
    scale = 1 / np.linalg.norm(a)
    # p1 at 0, p2 at 1, p3 where the 3D shape puts it (counter-clockwise, so the rest comes out clockwise
    # in the plane and counter-clockwise on the sphere after the orientation-reversing projection).
    third = scale * np.array([a @ b / np.linalg.norm(a), np.linalg.norm(np.cross(a, b)) / np.linalg.norm(a)])
    boundary = np.zeros((n, 2))
    boundary[p2] = [1, 0]
    boundary[p3] = third
    z = _dirichlet_solve(cotan_laplacian(vertices, faces), boundary, [p1, p2, p3])
    z -= z.mean(axis=0)
    # Scale the plane so the big triangle (around the north pole) and the triangle nearest the south
    # pole get about the same size on the sphere.
    S = _inverse_stereographic(z)
    with np.errstate(divide="ignore", invalid="ignore"):
        w = S[:, :2] / (1 + S[:, 2:])                          # south-pole stereographic coordinates
    order = np.argsort(np.linalg.norm(z[faces], axis=2).sum(axis=1))
    inner = order[1] if order[0] == big else order[0]

    def mean_side(points, face):
        corners = points[faces[face]]
        return np.linalg.norm(corners - np.roll(corners, 1, axis=0), axis=1).mean()

    north_side, south_side = mean_side(z, big), mean_side(w, inner)
    if np.isfinite(south_side) and south_side > 0:
        z *= np.sqrt(north_side * south_side) / north_side
    S = _inverse_stereographic(z)

    # Step 2: quasi-conformal correction around the north pole, in south-pole stereographic coordinates.
    by_height = np.argsort(S[:, 2])
    plane = S[:, :2] / (1 + S[:, 2:])
    mu = beltrami_coefficient(plane, faces, vertices)
    count = max(round(n * fixed_fraction), 3)
    for attempt in range(2):
        fixed = by_height[:min(n, count)]
        with np.errstate(divide="ignore", invalid="ignore"):
            try:
                corrected = linear_beltrami_solver(plane, faces, mu, fixed, plane[fixed])
            except RuntimeError:                                # singular factorisation
                corrected = np.full_like(plane, np.nan)
        if np.isfinite(corrected).all():
            break
        count *= 5
    else:
        corrected = plane
    return _inverse_stereographic(corrected, from_pole=-1.0)


# --- Kazhdan, Solomon & Ben-Chen (2012) ----------------------------------------------------------------

def _normalise_surface(X, faces):
    """Translate the area-weighted centroid to the origin and scale the total area to 4 pi."""
    areas = triangle_areas_3d(X, faces)
    centre = (areas[:, None] * X[faces].mean(axis=1)).sum(axis=0) / areas.sum()
    return (X - centre) * np.sqrt(4 * np.pi / areas.sum())


def cmcf_map(vertices, faces, steps=20, time_step=1.0):
    """Conformalized mean curvature flow (Kazhdan, Solomon & Ben-Chen 2012), then central projection.

    "Can mean-curvature flow be modified to be non-singular?", Computer Graphics Forum 31(5). Each
    implicit step solves ``(M_t + dt K_0) x_{t+1} = M_t x_t``, where K_0 is the cotangent Laplacian of
    the *original* mesh (the paper's modification: only the mass matrix M_t, here lumped, follows the
    flow, which removes the singularities of plain mean curvature flow and makes the flow conformal).
    After every step the surface is recentred and rescaled to area 4 pi (the flow shrinks it), so
    ``time_step`` is in units of a unit sphere. A genus-0 surface flows toward a round sphere; the
    result is the central projection of the flowed vertices from their area-weighted centroid.

    Parameters
    ----------
    vertices : (n, 3) float array
    faces : (t, 3) int array
    steps : int
        Number of implicit steps.
    time_step : float
        Step size, relative to a surface of area 4 pi.

    Returns
    -------
    (n, 3) float array of unit vectors.

    Examples
    --------
    >>> from sphere_nlp.shapes import cylinder
    >>> from sphere_nlp.certify import certify
    >>> V, F = cylinder()
    >>> certify(cmcf_map(V, F), F).valid
    True
    """
    faces = np.asarray(faces, dtype=np.int64)
    X = _normalise_surface(np.asarray(vertices, dtype=float), faces)
    stiffness = cotan_laplacian(X, faces)
    for _ in range(steps):
        mass = lumped_mass(X, faces)
        with np.errstate(divide="ignore", invalid="ignore"):
            X = spla.splu((mass + time_step * stiffness).tocsc()).solve(mass @ X)
            X = _normalise_surface(X, faces)
        if not np.isfinite(X).all():
            break
    with np.errstate(divide="ignore", invalid="ignore"):
        return X / np.linalg.norm(X, axis=1, keepdims=True)


# --- the convex embedding -----------------------------------------------------------------------------

def tutte_projection(vertices, faces):
    """Tutte embedding lifted to a convex polytope and projected centrally (valid by construction).

    :func:`sphere_nlp.embedding.convex_embedding` with cotangent weights: the feasible start of
    sphere_nlp's solve, as the simplest baseline. Valid in exact arithmetic; on long-limbed meshes
    triangles can shrink below floating-point resolution, which the certificate reports.

    Examples
    --------
    >>> from sphere_nlp.shapes import cylinder
    >>> from sphere_nlp.certify import certify
    >>> V, F = cylinder()
    >>> certify(tutte_projection(V, F), F).valid
    True
    """
    from .connectivity import build_connectivity
    from .embedding import convex_embedding

    vertices = np.asarray(vertices, dtype=float)
    faces = np.asarray(faces, dtype=np.int64)
    return convex_embedding(build_connectivity(faces, len(vertices)), vertices)
