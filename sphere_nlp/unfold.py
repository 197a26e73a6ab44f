"""Unfold solved spherical angles into vertex positions on the unit sphere (section 5 of the paper).

Arc lengths come from the angles of each triangle; the first triangle is placed directly, then every
other vertex is placed from a triangle whose other two vertices are already placed, at the
intersection of the unit sphere with two spheres whose radii are the chord lengths.

The walk is breadth-first from a central triangle (one of least eccentricity in the triangle graph),
level by level, so paths from the seed are as short as the mesh allows and each level is placed in one
vectorised step.
"""

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import shortest_path


def half_chords_squared(angles, excess=None):
    """sin^2(a / 2) for the arc a opposite every corner, from the triangle's own angles, (t, 3).

    Uses the half-angle form of the spherical cosine rule,
    sin^2(a/2) = sin(E/2) cos(S - A) / (sin B sin C), with E the excess and S = (pi + E) / 2, which stays
    accurate for short arcs where cos a is close to 1 and the plain cosine rule loses digits.
    Pass the solved ``excess`` when it is known: recomputing E = A + B + C - pi loses all its digits
    for tiny triangles (E of 1e-13 next to angles of 1).
    """
    A = np.asarray(angles, float)
    B, C = np.roll(A, -1, axis=1), np.roll(A, -2, axis=1)
    if excess is None:
        excess = A.sum(1) - np.pi
    excess = np.asarray(excess, float)[:, None]
    # cos(S - A) = sin(A - E/2): the same quantity without the cancellation near pi/2.
    return np.sin(excess / 2) * np.sin(A - excess / 2) / (np.sin(B) * np.sin(C))


def edge_chords(connectivity, angles, excess=None):
    """Chord length 2 sin(a/2) of every edge, averaged over its two triangles, (m,).

    Also returns the largest relative disagreement between the two triangles of an edge.
    """
    s2 = np.clip(half_chords_squared(angles, excess), 0.0, 1.0).ravel()
    chord = 2 * np.sqrt(s2)
    c = connectivity.edge_corner_indices()
    c1, c2 = chord[c[:, 0]], chord[c[:, 1]]
    mismatch = np.abs(c1 - c2) / np.maximum(np.maximum(c1, c2), 1e-300)
    return 0.5 * (c1 + c2), float(mismatch.max(initial=0.0))


def central_face(connectivity):
    """A triangle of (approximately) least eccentricity in the triangle adjacency graph."""
    t = connectivity.n_faces
    f1, f2 = connectivity.edge_faces.T
    graph = sp.coo_matrix((np.ones(len(f1)), (f1, f2)), shape=(t, t)).tocsr()
    d = shortest_path(graph, directed=False, unweighted=True, indices=0)
    far1 = int(np.argmax(d))
    d1 = shortest_path(graph, directed=False, unweighted=True, indices=far1)
    far2 = int(np.argmax(d1))
    d2 = shortest_path(graph, directed=False, unweighted=True, indices=far2)
    return int(np.argmin(np.maximum(d1, d2)))


def _place_third(pu, pv, chord_uw, chord_vw):
    """Unit vectors w with |w - pu| = chord_uw, |w - pv| = chord_vw and det[pu, pv, w] > 0 (vectorised)."""
    cu = 1 - chord_uw ** 2 / 2            # w . pu
    cv = 1 - chord_vw ** 2 / 2            # w . pv
    g = np.einsum("ij,ij->i", pu, pv)
    denom = np.maximum(1 - g * g, 1e-300)
    a = (cu - g * cv) / denom
    b = (cv - g * cu) / denom
    normal = np.cross(pu, pv)             # |normal|^2 = 1 - g^2
    in_plane = a * a + b * b + 2 * a * b * g
    c = np.sqrt(np.maximum(1 - in_plane, 0) / denom)
    w = a[:, None] * pu + b[:, None] * pv + c[:, None] * normal
    return w / np.linalg.norm(w, axis=1, keepdims=True)


def _place_by_angle(pu, pv, angle_at_u, chord_uw):
    """Unit vectors w at chord ``chord_uw`` from pu, at spherical angle ``angle_at_u`` from the arc
    u -> v, counter-clockwise seen from outside (vectorised).

    Works with differences from pu, never with dot products close to 1, so tiny triangles keep
    their relative accuracy (intersecting spheres loses it: 1 - (pu.pv)^2 cancels).
    """
    d = pv - pu
    toward_v = d - np.einsum("ij,ij->i", d, pu)[:, None] * pu       # tangent at pu toward v
    toward_v /= np.linalg.norm(toward_v, axis=1, keepdims=True)
    left = np.cross(pu, toward_v)
    half = np.clip(chord_uw / 2, 0.0, 1.0)
    arc = 2 * np.arcsin(half)
    direction = np.cos(angle_at_u)[:, None] * toward_v + np.sin(angle_at_u)[:, None] * left
    # w = cos(arc) pu + sin(arc) direction, written as pu + (small terms) for accuracy.
    w = pu + np.sin(arc)[:, None] * direction - (2 * half ** 2)[:, None] * pu
    return w / np.linalg.norm(w, axis=1, keepdims=True)


def unfold(connectivity, angles, seed_face=None, excess=None):
    """Vertex positions on the unit sphere that realise the solved angles.

    Parameters
    ----------
    connectivity : Connectivity
    angles : (t, 3) array
        Solved spherical angles (they must satisfy (6)-(8)).
    seed_face : int, optional
        First triangle to place; default :func:`central_face`.
    excess : (t,) array, optional
        Solved excesses (more accurate than recomputing them from the angles).

    Returns
    -------
    positions : (n, 3) array of unit vectors
    info : dict
        ``seed_face``, ``levels`` (breadth-first levels walked), ``edge_chord_mismatch`` (largest
        relative disagreement of an edge's chord between its two triangles).

    Examples
    --------
    >>> from sphere_nlp.shapes import octahedron
    >>> from sphere_nlp.connectivity import build_connectivity
    >>> V, F = octahedron()
    >>> X, info = unfold(build_connectivity(F, 6), np.full((8, 3), np.pi / 2))
    >>> bool(np.allclose(np.abs(X).max(1), 1))
    True
    """
    F = connectivity.faces
    n = connectivity.n_vertices
    chords, mismatch = edge_chords(connectivity, angles, excess)
    # Lookup of chord by vertex pair through a sparse matrix (symmetric).
    e = connectivity.edges
    chord_of = sp.coo_matrix((np.r_[chords, chords], (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])),
                             shape=(n, n)).tocsr()

    def chord(u, v):
        return np.asarray(chord_of[u, v]).ravel()

    seed = central_face(connectivity) if seed_face is None else int(seed_face)
    a, b, c = F[seed]
    A = np.asarray(angles, float)[seed]
    positions = np.zeros((n, 3))
    placed = np.zeros(n, bool)
    # First triangle: a at the north pole, b along the meridian through +x, c by the angle at a.
    ab = 2 * np.arcsin(min(chord([a], [b])[0] / 2, 1.0))
    ac = 2 * np.arcsin(min(chord([a], [c])[0] / 2, 1.0))
    positions[a] = [0, 0, 1]
    positions[b] = [np.sin(ab), 0, np.cos(ab)]
    positions[c] = [np.sin(ac) * np.cos(A[0]), np.sin(ac) * np.sin(A[0]), np.cos(ac)]
    placed[[a, b, c]] = True

    levels = 0
    while not placed.all():
        count = placed[F].sum(1)
        frontier = np.flatnonzero(count == 2)
        if len(frontier) == 0:
            raise RuntimeError("unfolding walk stalled: the triangle graph is not connected")
        Ff = F[frontier]
        missing = np.argmin(placed[Ff], axis=1)          # local index of the unplaced vertex
        rows = np.arange(len(frontier))
        w = Ff[rows, missing]
        u = Ff[rows, (missing + 1) % 3]                  # (u, v, w) is in the face's cyclic order
        v = Ff[rows, (missing + 2) % 3]
        angle_at_u = np.asarray(angles, float)[frontier, (missing + 1) % 3]
        w, first = np.unique(w, return_index=True)      # one triangle per new vertex
        u, v, angle_at_u = u[first], v[first], angle_at_u[first]
        # Seen from outside, w lies counter-clockwise of the arc u -> v by the angle at u.
        positions[w] = _place_by_angle(positions[u], positions[v], angle_at_u, chord(u, w))
        placed[w] = True
        levels += 1
    return positions, {"seed_face": seed, "levels": levels, "edge_chord_mismatch": mismatch}
