"""A valid spherical triangulation of any closed genus-0 mesh, used as a feasible starting point.

Construction (exact in exact arithmetic, by Tutte's and Maxwell-Cremona's theorems):

1. Remove one triangle and embed the rest in the plane inside it with a Tutte embedding (positive,
   symmetric edge weights; each interior vertex is the weighted mean of its neighbours). The result
   is a planar triangulation with no fold-overs.
2. The weights are an equilibrium stress of that framework (the three outer edges get the
   compressions that balance the outer vertices). Lifting it (Maxwell-Cremona) gives heights that
   make the triangulation the boundary of a convex polytope, with the removed triangle as its top face.
3. Central projection from a point inside the polytope maps every face to a spherical triangle with
   the right orientation, and the faces tile the sphere once.

The angles of this triangulation satisfy every constraint of the NLP, so a solve started from them
starts feasible. Because Tutte-type embeddings shrink some regions exponentially, the triangles can
become tiny on large, long-limbed meshes; what survives floating point is checked by the caller.
"""

import numpy as np
import scipy.sparse as sp

from . import interrupts, sparse_lu


def _rot90(v):
    return np.stack([-v[..., 1], v[..., 0]], axis=-1)


def edge_weights(vertices, connectivity, kind="cotan"):
    """Positive symmetric edge weights: clamped cotangent weights, or uniform ones."""
    if kind == "uniform" or vertices is None:
        return np.ones(connectivity.n_edges)
    from .geometry import corner_angles

    cot = 1 / np.tan(np.clip(corner_angles(vertices, connectivity.faces), 1e-6, np.pi - 1e-6))
    c = connectivity.edge_corner_indices()
    w = 0.5 * (cot.ravel()[c[:, 0]] + cot.ravel()[c[:, 1]])
    # Clamp to keep Tutte's theorem (positive weights), relative to the typical weight.
    return np.maximum(w, 1e-3 * np.median(np.abs(w)))


def graph_laplacian(connectivity, weights):
    """The (n, n) CSR Laplacian D - W of the edge graph with the given edge weights."""
    n = connectivity.n_vertices
    e = connectivity.edges
    W = sp.coo_matrix((np.r_[weights, weights], (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])),
                      shape=(n, n)).tocsr()
    return (sp.diags(np.asarray(W.sum(1)).ravel()) - W).tocsr()


def planar_tutte(connectivity, weights, outer_face):
    """Tutte embedding with the given outer face on an equilateral triangle; (n, 2) positions."""
    n = connectivity.n_vertices
    L = graph_laplacian(connectivity, weights)
    outer = connectivity.faces[outer_face]
    angles = np.pi / 2 + 2 * np.pi * np.arange(3) / 3
    P = np.zeros((n, 2))
    # The outer face is clockwise in the plane so the others come out counter-clockwise.
    P[outer] = np.c_[np.cos(angles), np.sin(angles)][::-1]
    inner = np.setdiff1d(np.arange(n), outer)
    L = L.tocsr()
    rhs = -L[inner][:, outer] @ P[outer]
    P[inner] = sparse_lu.solve(L[inner][:, inner], rhs)
    return P


def punctured_embedding(connectivity, vertex=None):
    """Valid spherical positions with one vertex at the north pole and its neighbours on the equator.

    The vertex's 1-ring goes, evenly spaced, onto the unit circle; the rest is a uniform Tutte
    embedding inside it (valid: a convex boundary, Tutte 1963), mapped to the southern hemisphere by
    the inverse stereographic projection, which keeps planar orientations; the removed vertex's
    triangles fill the northern hemisphere. Default ``vertex``: one of largest degree, whose ring,
    with a triangle as the boundary (:func:`convex_embedding`), shrinks exponentially along
    itself: a degree-1,000 cap falls below double precision.

    Examples
    --------
    >>> from sphere_nlp.shapes import octahedron
    >>> from sphere_nlp.connectivity import build_connectivity
    >>> from sphere_nlp.certify import certify
    >>> V, F = octahedron()
    >>> certify(punctured_embedding(build_connectivity(F, len(V))), F).valid
    True
    """
    faces = connectivity.faces
    n = connectivity.n_vertices
    if vertex is None:
        vertex = int(np.argmax(connectivity.vertex_degree))
    # The ring in order: each face (vertex, a, b), rotated to start at the vertex, gives a -> b.
    at = np.flatnonzero((faces == vertex).any(axis=1))
    rotated = [np.roll(f, -int(np.flatnonzero(f == vertex)[0])) for f in faces[at]]
    following = {int(a): int(b) for _, a, b in rotated}
    ring = [next(iter(following))]
    while len(ring) < len(following):
        ring.append(following[ring[-1]])
    ring = np.array(ring)
    # Clockwise in the plane, so that the triangles inside come out counter-clockwise as the
    # outer face does in planar_tutte; the orientation is checked below anyway.
    angles = -2 * np.pi * np.arange(len(ring)) / len(ring)
    plane = np.zeros((n, 2))
    plane[ring] = np.c_[np.cos(angles), np.sin(angles)]
    L = graph_laplacian(connectivity, np.ones(len(connectivity.edges)))
    inner = np.setdiff1d(np.arange(n), np.r_[ring, vertex])
    if len(inner):
        rhs = -L[inner][:, ring] @ plane[ring]
        plane[inner] = sparse_lu.solve(L[inner][:, inner], rhs)
    r2 = np.sum(plane ** 2, axis=1, keepdims=True)
    X = np.c_[2 * plane, r2 - 1] / (r2 + 1)
    X[vertex] = (0.0, 0.0, 1.0)
    from .certify import signed_solid_angles
    if np.sum(signed_solid_angles(X, faces)) < 0:
        X[:, 0] = -X[:, 0]
    return X


def convex_lift(connectivity, planar, weights, outer_face):
    """Maxwell-Cremona heights for a planar equilibrium framework, (n,) array.

    Interior vertices are in equilibrium by construction; the outer edges get the stresses that
    balance the three outer vertices.
    """
    F = connectivity.faces
    e = connectivity.edges
    n, t = connectivity.n_vertices, connectivity.n_faces
    w = weights.astype(float).copy()
    outer = F[outer_face]
    outer_edge = {tuple(e[k]): k for k in np.flatnonzero(np.isin(e, outer).all(1))}
    w[list(outer_edge.values())] = 0.0
    # Net force on each outer vertex from its other edges; balance it along the two outer edges.
    force = np.zeros((n, 2))
    for s, d in ((0, 1), (1, 0)):
        np.add.at(force, e[:, s], w[:, None] * (planar[e[:, d]] - planar[e[:, s]]))
    a, b, c = outer
    for v, (p, q) in ((a, (b, c)), (b, (c, a)), (c, (a, b))):
        M = np.c_[planar[p] - planar[v], planar[q] - planar[v]]
        wp, wq = np.linalg.solve(M, -force[v])
        # Each outer edge is solved twice (from both ends); equilibrium makes them agree, so average.
        for other, value in ((p, wp), (q, wq)):
            k = outer_edge[tuple(sorted((v, other)))]
            w[k] += value / 2
    # Face gradients g_f: across edge i->j with face f on its left and g on its right,
    # g_f - g_g = w_ij * rot90(p_j - p_i). Propagate breadth-first from the outer face (g = 0).
    half_edge_face = np.repeat(np.arange(t), 3)
    tails = np.roll(F, -1, axis=1).ravel()        # directed edge opposite corner j: j+1 -> j+2
    heads = np.roll(F, -2, axis=1).ravel()
    c_idx = connectivity.edge_corner_indices()
    # For each edge, the face on the left of (tail -> head) of its first corner is that corner's face.
    left = half_edge_face[c_idx[:, 0]]
    right = half_edge_face[c_idx[:, 1]]
    jump = w[:, None] * _rot90(planar[heads[c_idx[:, 0]]] - planar[tails[c_idx[:, 0]]])
    offset_jump = -np.einsum("ij,ij->i", jump, planar[tails[c_idx[:, 0]]])
    gradient = np.full((t, 2), np.nan)
    offset = np.full(t, np.nan)
    gradient[outer_face], offset[outer_face] = 0.0, 0.0
    known = np.zeros(t, bool)
    known[outer_face] = True
    while not known.all():
        forward = known[right] & ~known[left]     # right known -> left = right + jump
        backward = known[left] & ~known[right]
        if not (forward.any() or backward.any()):
            raise RuntimeError("face graph is not connected")
        k = np.flatnonzero(forward)
        f, first = np.unique(left[k], return_index=True)
        gradient[f] = gradient[right[k[first]]] + jump[k[first]]
        offset[f] = offset[right[k[first]]] + offset_jump[k[first]]
        known[f] = True
        k = np.flatnonzero(backward & ~known[right])
        f, first = np.unique(right[k], return_index=True)
        gradient[f] = gradient[left[k[first]]] - jump[k[first]]
        offset[f] = offset[left[k[first]]] - offset_jump[k[first]]
        known[f] = True
    heights = np.zeros(n)
    heights[F.ravel()] = (np.einsum("tj,tkj->tk", gradient, planar[F]) + offset[:, None]).ravel()
    return heights


def convex_embedding(connectivity, vertices=None, weights="cotan", outer_face=None):
    """Valid spherical positions for the mesh's connectivity (see the module docstring).

    Parameters
    ----------
    connectivity : Connectivity
    vertices : (n, 3) array, optional
        3D positions, used only for the cotangent weights (which follow the shape better than
        uniform ones and so shrink limbs less).
    weights : {"cotan", "uniform"}
    outer_face : int, optional
        The triangle removed for the planar embedding; default the one of largest 3D area.

    Returns
    -------
    (n, 3) array of unit vectors.

    Examples
    --------
    >>> from sphere_nlp.shapes import cylinder
    >>> from sphere_nlp.connectivity import build_connectivity
    >>> from sphere_nlp.certify import certify
    >>> V, F = cylinder()
    >>> certify(convex_embedding(build_connectivity(F, len(V)), V), F).valid
    True
    """
    w = edge_weights(vertices, connectivity, weights)
    if outer_face is None:
        if vertices is not None:
            from .geometry import triangle_areas
            outer_face = int(np.argmax(triangle_areas(vertices, connectivity.faces)))
        else:
            outer_face = 0
    planar = planar_tutte(connectivity, w, outer_face)
    heights = convex_lift(connectivity, planar, w, outer_face)
    P = np.c_[planar, heights]
    # Make the lift's scale comparable to the plane's, then project from inside the polytope.
    span = np.ptp(heights)
    if span > 0:
        P[:, 2] *= 1.0 / span
    centre = P.mean(axis=0)
    X = P - centre
    X /= np.linalg.norm(X, axis=1, keepdims=True)
    from .certify import signed_solid_angles
    if np.sum(signed_solid_angles(X, connectivity.faces)) < 0:
        X[:, 0] = -X[:, 0]                      # the lift came out mirrored
    return X


def _ball_automorphism(X, c):
    """The Mobius transformation of the unit sphere taking the ball point c to the origin."""
    # x -> ((1-|c|^2)(x-c) - |x-c|^2 c) / (1 - 2<x,c> + |c|^2 |x|^2), with |x| = 1.
    d = X - c
    Y = ((1 - c @ c) * d - np.einsum("ij,ij->i", d, d)[:, None] * c) / (1 - 2 * X @ c + c @ c)[:, None]
    return Y / np.linalg.norm(Y, axis=1, keepdims=True)


def mobius_centre(positions, weights=None, max_iter=100, tol=1e-9):
    """Move points on the unit sphere by a Mobius transformation until their weighted mean is 0.

    A spherical map is only defined up to Mobius transformations for conformal purposes, and a
    Tutte-type or harmonic map typically crowds most of the mesh into a small cap. Centring spreads
    it over the sphere (each step is the hyperbolic translation taking the current weighted mean c
    to the origin, damped by 1/2), which moves the start much closer to every target mode. Small
    triangles keep their orientation; the caller still certifies the result.

    Parameters
    ----------
    positions : (n, 3) array of unit vectors
    weights : (n,) array, optional
        Non-negative weights (e.g. vertex areas of the 3D mesh); uniform by default.

    Returns
    -------
    (n, 3) array of unit vectors.

    Examples
    --------
    >>> X = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [-1, 0, 0.0]])
    >>> bool(np.linalg.norm(mobius_centre(X).mean(0)) < 1e-8)
    True
    """
    X = np.asarray(positions, float).copy()
    w = np.ones(len(X)) if weights is None else np.asarray(weights, float)
    w = w / w.sum()
    for _ in range(max_iter):
        c = w @ X
        if np.linalg.norm(c) < tol:
            break
        X = _ball_automorphism(X, 0.5 * c)
    return X


def excess_gauge(positions, faces, max_iter=50, tol=1e-4):
    """Move a spherical triangulation by Mobius transformations to minimise sum(excess^2).

    For small triangles the spherical angles are the flat ones plus about e/3 each, so the
    angle objective (9) changes under a Mobius transformation by about sum(e^2)/3: this picks
    the Mobius normalisation of the angle modes' optimum, which on adaptively refined meshes is
    far from the area-centred one (nefertiti.obj: log excesses of the start differ from the
    optimum's by a dipole of size 2.1, mean 1.6; after this by 0.08, mean 0.05). Each step is a
    boost against the e^2-weighted mean of the triangle centres (the direction of decrease),
    halved until sum(e^2) decreases and every triangle stays positively oriented.

    Returns
    -------
    (n, 3) array of unit vectors; ``positions`` itself if no step was taken.
    """
    from .certify import signed_solid_angles

    X = np.asarray(positions, float)
    faces = np.asarray(faces)
    e = signed_solid_angles(X, faces)
    if not (e > 0).all():
        return X
    f = e @ e
    for _ in range(max_iter):
        if interrupts.deadline_passed():        # the run's time is up: any step so far is valid
            break
        centres = X[faces[:, 0]] + X[faces[:, 1]] + X[faces[:, 2]]       # no (t, 3, 3) gather
        centres /= np.linalg.norm(centres, axis=1, keepdims=True)
        g = (e * e) @ centres / f
        if np.linalg.norm(g) < tol:
            break
        step = 0.5
        while step > 1e-3:
            Y = _ball_automorphism(X, -step * g)
            e_new = signed_solid_angles(Y, faces)
            if (e_new > 0).all() and e_new @ e_new < f:
                break
            step /= 2
        else:
            break
        X, e, f = Y, e_new, e_new @ e_new
    return X
