"""Unfold solved spherical angles into vertex positions on the unit sphere (section 5 of the paper).

Two stages:

1. **Walk.** Breadth-first from a central triangle (one of least eccentricity in the triangle graph),
   level by level, so paths from the seed are as short as the mesh allows and each level is placed
   in one vectorised step. A new vertex ``w`` of a triangle ``(w, u, v)`` whose ``u`` and ``v`` are
   placed goes where the unit sphere meets the two spheres of radius the chords uw and vw (chords
   from the half-angle formula; lengths from data keep errors from compounding). In triangles too
   small for their excess to carry a scale, the chords come from the sine law on the placed side
   instead. A vertex is placed from its best-conditioned triangles (sin of the angle at ``w``),
   ill-conditioned ones wait a level, and placements from several triangles of a level are averaged
   with weights ``sin^2`` (the paper's averaging idea). If a level completes triangles whose angles
   are off by more than ``WALK_REPAIR_ERROR``, the completed region is corrected (stage 2) before
   the walk goes on, and so it is before a level that only ill-conditioned triangles reach, which
   would multiply the error so far (``WALK_FORCED_REPAIR_ERROR``); well-shaped meshes never need it.
2. **Correction.** The walk accumulates error with depth (the paper's "numerical error, which
   increases with the number of triangles"). Gauss-Newton on all corner-angle residuals
   ``angle(positions) - solved angle`` removes it: each vertex moves in its tangent plane and is
   retracted onto the sphere by normalising; the normal equations are sparse (2 unknowns per vertex,
   one 6x6 block per triangle) and solved by sparse LU once; later steps solve them by conjugate
   gradients preconditioned with that factorisation, refactorising only when it has gone stale.
   A tiny Levenberg-Marquardt damping fixes the 3 rotational degrees of freedom (the gradient has no
   component along them). Fitting angles rather than chords matters: the angles are what the NLP
   guarantees, and they fix the shape of even the smallest triangles, whose chords they do not.
"""

import time

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import reverse_cuthill_mckee, shortest_path

from . import sparse_lu
from .certify import spherical_angles
from .connectivity import vertex_graph
from .geometry import cross
from .heap import arrays_on_heap


def half_chords_squared(angles, excess=None):
    """sin^2(a / 2) for the arc a opposite every corner, from the triangle's own angles, (t, 3).

    Uses the half-angle form of the spherical cosine rule,
    sin^2(a/2) = sin(E/2) cos(S - A) / (sin B sin C), with E the excess and S = (pi + E) / 2, which stays
    accurate for short arcs where cos a is close to 1 and the plain cosine rule loses digits.
    Pass the solved ``excess`` when it is known: recomputing E = A + B + C - pi loses all its digits
    for tiny triangles (E of 1e-13 next to angles of 1); the log-chord solve carries E exactly.

    Examples
    --------
    >>> s2 = half_chords_squared(np.full((1, 3), np.pi / 2))   # octant: every arc is pi / 2
    >>> bool(np.allclose(s2, 0.5))
    True
    """
    A = np.asarray(angles, float)
    B, C = np.roll(A, -1, axis=1), np.roll(A, -2, axis=1)
    excess = (A.sum(1) - np.pi if excess is None else np.asarray(excess, float))[:, None]
    # cos(S - A) = sin(A - E/2): the same quantity without the cancellation near pi/2.
    return np.sin(excess / 2) * np.sin(A - excess / 2) / (np.sin(B) * np.sin(C))


def edge_chords(connectivity, angles, excess=None):
    """Chord length 2 sin(a/2) of every edge, averaged over its two triangles, (m,).

    A triangle's chords are only as good as its excess E = sum of angles - pi, a small difference of
    large numbers: an angle error d makes them off by about d / E relative. The two estimates are
    therefore weighted by E^2 (inverse variance), so a long edge shared by a needle and a normal
    triangle takes the normal one's length. Also returns the largest relative disagreement between
    the two triangles of an edge, which for small triangles mostly measures how poorly angles
    determine scale, not an error in the angles.

    Examples
    --------
    >>> from sphere_nlp.shapes import octahedron
    >>> from sphere_nlp.connectivity import build_connectivity
    >>> V, F = octahedron()
    >>> chords, mismatch = edge_chords(build_connectivity(F, 6), np.full((8, 3), np.pi / 2))
    >>> bool(np.allclose(chords, np.sqrt(2))), mismatch < 1e-15
    (True, True)
    """
    c1, c2 = _chord_pairs(connectivity, angles, excess)
    if excess is None:
        excess = np.asarray(angles, float).sum(1) - np.pi
    w1, w2 = (np.maximum(excess[f], 1e-300) ** 2 for f in connectivity.edge_faces.T)
    return ((w1 * c1 + w2 * c2) / (w1 + w2),
            float(_edge_mismatch(connectivity, angles, excess).max(initial=0.0)))


def _chord_pairs(connectivity, angles, excess=None):
    """Chord of every edge as computed from each of its two triangles, two (m,) arrays."""
    chord = 2 * np.sqrt(np.clip(half_chords_squared(angles, excess), 0.0, 1.0).ravel())
    c = connectivity.edge_corner_indices()
    return chord[c[:, 0]], chord[c[:, 1]]


def _edge_mismatch(connectivity, angles, excess=None):
    """Relative disagreement of every edge's chord between its two triangles, (m,)."""
    c1, c2 = _chord_pairs(connectivity, angles, excess)
    return np.abs(c1 - c2) / np.maximum(np.maximum(c1, c2), 1e-300)


def central_face(connectivity, acceptable=None):
    """A triangle of (approximately) least eccentricity in the triangle adjacency graph.

    Two sweeps find a pair of far-apart triangles; the face minimising the larger distance to them
    is near the graph's centre, so the walk from it is about half the diameter deep. With
    ``acceptable`` (a boolean mask over faces, not all False) the choice is among those faces.
    """
    t = connectivity.n_faces
    f1, f2 = connectivity.edge_faces.T
    graph = sp.coo_matrix((np.ones(len(f1)), (f1, f2)), shape=(t, t)).tocsr()
    d = shortest_path(graph, directed=False, unweighted=True, indices=0)
    far1 = int(np.argmax(d))
    d1 = shortest_path(graph, directed=False, unweighted=True, indices=far1)
    far2 = int(np.argmax(d1))
    d2 = shortest_path(graph, directed=False, unweighted=True, indices=far2)
    eccentricity = np.maximum(d1, d2)
    if acceptable is not None and np.any(acceptable):
        eccentricity = np.where(acceptable, eccentricity, np.inf)
    return int(np.argmin(eccentricity))


def _unit(x):
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def _place_by_angle(pu, pv, angle_at_u, chord_uw):
    """Unit vectors w at chord ``chord_uw`` from pu, at spherical angle ``angle_at_u`` from the arc
    u -> v, counter-clockwise seen from outside (vectorised).

    Works with differences from pu, never with dot products close to 1, so tiny triangles keep
    their relative accuracy (intersecting spheres does not: 1 - (pu.pv)^2 cancels; on the knight's
    equal-angles map, with excesses of 2e-13, that walk flipped 22 triangles).
    """
    d = pv - pu
    toward_v = d - np.einsum("ij,ij->i", d, pu)[:, None] * pu       # tangent at pu toward v
    length = np.linalg.norm(toward_v, axis=1, keepdims=True)
    # u and v placed on one point in double precision (a collapsed edge) give no direction: any
    # tangent at pu will do, rather than 0 / 0 making w, and every vertex placed from it, NaN.
    collapsed = length[:, 0] == 0
    if collapsed.any():
        toward_v[collapsed], length[collapsed] = tangent_bases(pu[collapsed])[:, :, 0], 1.0
    toward_v /= length
    left = cross(pu, toward_v)
    half = np.clip(chord_uw / 2, 0.0, 1.0)
    arc = 2 * np.arcsin(half)
    direction = np.cos(angle_at_u)[:, None] * toward_v + np.sin(angle_at_u)[:, None] * left
    # w = cos(arc) pu + sin(arc) direction, written as pu + (small terms) for accuracy.
    w = pu + np.sin(arc)[:, None] * direction - (2 * half ** 2)[:, None] * pu
    return w / np.linalg.norm(w, axis=1, keepdims=True)


def _seed_positions(angles_seed, chords_seed):
    """Positions of the first triangle: corner 0 at the north pole, corner 1 on the +x meridian.

    ``chords_seed[j]`` is the chord opposite corner j.
    """
    arc = 2 * np.arcsin(np.minimum(np.asarray(chords_seed) / 2, 1.0))
    ab, ac = arc[2], arc[1]
    A = angles_seed[0]
    return np.array([[0.0, 0.0, 1.0],
                     [np.sin(ab), 0.0, np.cos(ab)],
                     [np.sin(ac) * np.cos(A), np.sin(ac) * np.sin(A), np.cos(ac)]])


def corner_edges(connectivity):
    """Edge index opposite every flat corner 3 * i + j, (3t,)."""
    corners = connectivity.edge_corner_indices()
    out = np.empty(3 * connectivity.n_faces, np.int64)
    out[corners[:, 0]] = out[corners[:, 1]] = np.arange(connectivity.n_edges)
    return out


# A vertex is placed from a triangle only when sin(angle at the vertex) is at least this, unless no
# vertex of the level qualifies: the chord-sphere intersection loses ~1/sin of that angle in accuracy.
WELL_CONDITIONED_SIN = 0.2

# An edge whose chord, computed from each of its two triangles, disagrees by more than this (relative)
# has an unreliable length: its triangles are too small for their excess to carry the scale. A data
# chord off by this much costs about as much angle error once, locally; the sine-law fallback instead
# compounds along the walk, so the threshold is loose.
RELIABLE_CHORD_MISMATCH = 1e-4


def _sine_law_chords(chord_uv, sin_u, sin_v, sin_w):
    """Chords uw and vw of a triangle (w, u, v) from its side uv and the sines of its angles.

    Spherical sine law sin(uw) / sin V = sin(vw) / sin U = sin(uv) / sin W, taking the arcs below
    pi / 2: used for small triangles only, where it holds the ratios the angles fix well. A sine
    outside [0, 1] (an angle past pi in a stopped solve's iterate) is clipped into that range, so
    the walk places something and the certificate, not a NaN, says the map failed.
    """
    sin_uv = np.sin(2 * np.arcsin(np.minimum(chord_uv / 2, 1.0)))
    arc_uw = np.arcsin(np.clip(sin_uv * sin_v / sin_w, 0.0, 1.0))
    arc_vw = np.arcsin(np.clip(sin_uv * sin_u / sin_w, 0.0, 1.0))
    return 2 * np.sin(arc_uw / 2), 2 * np.sin(arc_vw / 2)


# When a level completes a triangle whose angles are off by more than this (radians), the walk stops
# to run the correction on everything completed so far, then goes on from corrected positions: drift
# compounds along the walk on meshes of skinny triangles, and Gauss-Newton needs a close start. It
# sits above the local error that chords with RELIABLE_CHORD_MISMATCH cause.
WALK_REPAIR_ERROR = 1e-3

# ... but only after the placed region has grown by this factor since the last repair, so that the
# repairs cost a bounded multiple of one final correction,
WALK_REPAIR_GROWTH = 1.5

# ... unless the error passes this, when a growth by WALK_URGENT_GROWTH is enough.
WALK_URGENT_ERROR = 3e-2
WALK_URGENT_GROWTH = 1.1

# A level none of whose vertices has a well-conditioned triangle (a band of needles whose far
# vertices all sit at sharp corners) places them anyway, multiplying the error of the placed region by
# about 1 / sin(angle at w). Below WALK_REPAIR_ERROR that error is normally left for the final
# correction, but amplified it is not: on the Loop armadillo's original-areas map (173k vertices,
# corners of 0.007 rad at the far side of such bands) an error of 1.6e-4 became 2 pi and 41 flips.
# So before such a level the placed region is corrected whenever its error / sin would pass this.
WALK_FORCED_REPAIR_ERROR = 1e-5


def _max_angle_error(positions, faces, angles):
    """Largest |angle measured from positions - solved angle| over some faces (0 for none)."""
    corners = positions[faces].reshape(-1, 3)
    error = np.abs(spherical_angles(corners, np.arange(len(corners)).reshape(-1, 3)) - angles)
    return error.max(initial=0.0)


def walk(connectivity, angles, seed_face, chords=None, average=True, repair=True, excess=None,
         vertex_order=None):
    """Breadth-first placement of every vertex from two placed neighbours and two chord lengths.

    Chord lengths come from the triangles' angles (:func:`edge_chords`), except in triangles with an
    edge whose two estimates disagree (tiny triangles): there the sine law scales the placed side.
    That keeps the walk stable (lengths from data do not compound) where the data is good, and
    local where it is not.

    One loop of about 85 lines on purpose: the level's placements, their averaging and the repairs
    between levels all read and update the same placed set and front, which split into functions
    would be passed around whole.

    Parameters
    ----------
    connectivity : Connectivity
    angles : (t, 3) array
    seed_face : int
    chords : (m,) array, optional
        Chord length of every edge; default :func:`edge_chords` of the angles.
    average : bool
        Average the placements of a vertex from all triangles of its level that reach it, weighted
        by sin^2 of the angle at the vertex (the paper's averaging of unfolding sequences); otherwise
        use the best-conditioned one.
    repair : bool
        Correct the completed part of the mesh (:func:`correct`) whenever a level completes a
        triangle with an angle error above ``WALK_REPAIR_ERROR``, and before a level that only
        ill-conditioned triangles reach if the error so far, amplified, would pass
        ``WALK_FORCED_REPAIR_ERROR``.
    vertex_order : (n,) int array, optional
        The repairs' fill-reducing vertex order (``Connectivity.vertex_order``); default: each
        repair orders its part of the mesh itself.

    Returns
    -------
    positions : (n, 3) array of unit vectors
    levels : int
        Number of breadth-first levels (the depth of the walk).
    repairs : int
        Number of corrections run during the walk.

    Examples
    --------
    >>> from sphere_nlp.shapes import octahedron
    >>> from sphere_nlp.connectivity import build_connectivity
    >>> V, F = octahedron()
    >>> X, levels, repairs = walk(build_connectivity(F, 6), np.full((8, 3), np.pi / 2), 0)
    >>> bool(np.allclose(np.abs(X).max(1), 1)), levels, repairs
    (True, 1, 0)
    """
    F = connectivity.faces
    n, t = connectivity.n_vertices, connectivity.n_faces
    A = np.asarray(angles, float)
    edge_of_corner = corner_edges(connectivity)
    if chords is None:
        chords = edge_chords(connectivity, A, excess)[0]
    chord_at = chords[edge_of_corner].reshape(-1, 3)               # chord opposite each corner
    mismatch = _edge_mismatch(connectivity, A, excess)
    unreliable = (mismatch[edge_of_corner] > RELIABLE_CHORD_MISMATCH).reshape(-1, 3).any(1)
    sin_at = np.sin(A)
    # Faces around each vertex, to update the count of placed vertices per face incrementally.
    faces_of_vertex = sp.csr_matrix((np.ones(3 * t), (F.ravel(), np.repeat(np.arange(t), 3))), shape=(n, t))

    def touched_faces(vertices):
        return faces_of_vertex[vertices].indices

    positions = np.zeros((n, 3))
    placed = np.zeros(n, bool)
    count = np.zeros(t, np.int64)
    positions[F[seed_face]] = _seed_positions(A[seed_face], chord_at[seed_face])
    placed[F[seed_face]] = True
    n_placed = 3
    touched = touched_faces(F[seed_face])
    np.add.at(count, touched, 1)
    pending = np.zeros(0, np.int64)
    levels = repairs = 0
    placed_at_repair = 3
    # Every level costs in proportion to its own front only: these per-vertex scratch arrays are
    # zeroed where a level wrote them, not allocated afresh (at 692k vertices and 577 levels, full-size
    # work per level was most of the walk's time), and the largest angle error of the completed
    # triangles is kept up to date from each level's newly completed ones (their angles do not change
    # until a repair moves them; None: to be measured afresh after a repair).
    best = np.zeros(n)
    total = np.zeros((n, 3)) if average else None
    done_error = _max_angle_error(positions, F[[seed_face]], A[[seed_face]]) if repair else None
    while n_placed < n:
        frontier = np.union1d(pending, touched)
        frontier = frontier[count[frontier] == 2]
        if len(frontier) == 0:
            raise RuntimeError("unfolding walk stalled: the triangle graph is not connected")
        Ff = F[frontier]
        missing = np.argmin(placed[Ff], axis=1)          # local index of the unplaced vertex
        rows = np.arange(len(frontier))
        next_, prev = (missing + 1) % 3, (missing + 2) % 3
        w, u, v = Ff[rows, missing], Ff[rows, next_], Ff[rows, prev]   # (w, u, v) in cyclic order
        sin_w = sin_at[frontier, missing]
        np.maximum.at(best, w, sin_w)
        best_w = best[w]
        best[w] = 0.0
        ok = best_w >= WELL_CONDITIONED_SIN
        if repair and not ok.any() and n_placed > placed_at_repair:
            if done_error is None:
                done = np.flatnonzero(count == 3)
                done_error = _max_angle_error(positions, F[done], A[done])
            if not done_error <= WALK_FORCED_REPAIR_ERROR * best_w.max():
                positions = _repair_completed(F, A, count, positions, vertex_order)
                placed_at_repair = n_placed
                repairs += 1
                done_error = None
        pending = frontier
        if ok.any():                                    # defer ill-conditioned vertices to a later level
            frontier, rows, w, u, v, next_, prev, sin_w = (x[ok] for x in (frontier, rows, w, u, v, next_,
                                                                            prev, sin_w))
        chord_uw, chord_vw = chord_at[frontier, prev], chord_at[frontier, next_]
        local = unreliable[frontier]
        if local.any():
            fl = frontier[local]
            chord_uv = np.linalg.norm(positions[u[local]] - positions[v[local]], axis=1)
            chord_uw[local], chord_vw[local] = _sine_law_chords(
                chord_uv, sin_at[fl, next_[local]], sin_at[fl, prev[local]], sin_w[local])
        guess = _place_by_angle(positions[u], positions[v], A[frontier, next_], chord_uw)
        new = np.unique(w)
        if average:
            np.add.at(total, w, (sin_w ** 2)[:, None] * guess)
            positions[new] = _unit(total[new])
            total[new] = 0.0
        else:
            order = np.lexsort((-sin_w, w))               # best-conditioned triangle first per vertex
            first = order[np.r_[True, w[order][1:] != w[order][:-1]]]
            positions[w[first]] = guess[first]
        placed[new] = True
        n_placed += len(new)
        touched = touched_faces(new)
        np.add.at(count, touched, 1)
        pending = pending[count[pending] == 2]
        levels += 1
        if not repair:
            continue
        completed = np.unique(touched[count[touched] == 3])
        error = _max_angle_error(positions, F[completed], A[completed])
        if done_error is not None:
            done_error = np.maximum(done_error, error)
        growth = n_placed / placed_at_repair
        if growth >= WALK_URGENT_GROWTH:
            # Near the end the final correction will do: only urgent repairs then.
            tolerable = WALK_URGENT_ERROR if (growth < WALK_REPAIR_GROWTH or n_placed > 0.8 * n) \
                else WALK_REPAIR_ERROR
            if not error <= tolerable:
                positions = _repair_completed(F, A, count, positions, vertex_order)
                placed_at_repair = n_placed
                repairs += 1
                done_error = None
    return positions, levels, repairs


def _repair_completed(F, A, count, positions, vertex_order):
    """A walk's repair: the triangles completed so far (``count`` 3) corrected by Gauss-Newton,
    only well inside its reach for the next stretch of walk (the final correction does the rest)."""
    done = np.flatnonzero(count == 3)
    return correct(F[done], A[done], positions, max_iterations=20, tolerance=1e-8, slow_target=np.inf,
                   vertex_order=vertex_order)[0]


def tangent_bases(positions):
    """Two orthonormal tangent vectors at every unit vector, (n, 3, 2).

    Examples
    --------
    >>> X = np.array([[0.0, 0.0, 1.0], [0.6, 0.8, 0.0]])
    >>> T = tangent_bases(X)
    >>> bool(np.allclose(np.einsum("ni,nid->nd", X, T), 0))
    True
    """
    helper = np.zeros_like(positions)
    helper[np.arange(len(positions)), np.argmin(np.abs(positions), axis=1)] = 1.0
    e1 = _unit(cross(positions, helper))
    e2 = cross(positions, e1)
    return np.stack([e1, e2], axis=2)


def angle_gradients(positions, faces):
    """Gradient of every corner angle with respect to the three vertices of its triangle, (t, 3, 3, 3).

    ``G[i, j, k]`` is the gradient of the angle at corner ``j`` of face ``i`` with respect to the
    position of the vertex at corner ``k``, tangent to the sphere there. With a the corner's vertex and
    b, c the next ones, the angle is the azimuth of c minus that of b around a, so
    d/db = -(a x b)/|a x b|^2, d/dc = (a x c)/|a x c|^2, and d/da follows from invariance under
    rotations: (a.b)(a x b)/|a x b|^2 - (a.c)(a x c)/|a x c|^2.

    A corner whose vertex coincides with a neighbour in double precision (a triangle the walk
    collapsed to a point: a x b = 0) has no defined azimuth, so no gradient: its terms are zero,
    not the NaN of 0 / 0 that would spread through the normal matrix.
    """
    P = positions[faces]
    a, b, c = P, np.roll(P, -1, axis=1), np.roll(P, -2, axis=1)
    ab, ac = cross(a, b), cross(a, c)
    ab2 = np.einsum("tjk,tjk->tj", ab, ab)[..., None]
    ac2 = np.einsum("tjk,tjk->tj", ac, ac)[..., None]
    ab_scaled = np.divide(ab, ab2, out=np.zeros_like(ab), where=ab2 > 0)        # (a x b)/|a x b|^2
    ac_scaled = np.divide(ac, ac2, out=np.zeros_like(ac), where=ac2 > 0)
    g_b = -ab_scaled
    g_c = ac_scaled
    g_a = (np.einsum("tjk,tjk->tj", a, b)[..., None] * ab_scaled
           - np.einsum("tjk,tjk->tj", a, c)[..., None] * ac_scaled)
    G = np.empty(P.shape[:2] + (3, 3))
    j = np.arange(3)
    G[:, j, j] = g_a
    G[:, j, (j + 1) % 3] = g_b
    G[:, j, (j + 2) % 3] = g_c
    return G


def _angle_jacobian(positions, faces, bases):
    """Jacobian of the corner angles in tangent-plane coordinates: one (3, 6) block per face.

    Returns the blocks (t, 3, 6) and the unknown index of each of their columns (t, 6); vertex p has
    unknowns 2p and 2p + 1, its coordinates along ``bases[p]``.
    """
    G = angle_gradients(positions, faces)                          # (t, corner, slot, xyz)
    # J[t, j, k] = G[t, j, k] @ bases[faces[t, k]], as one batched matmul over (t, k), which is
    # faster than einsum on these 3x3 by 3x2 products.
    J = np.matmul(G.transpose(0, 2, 1, 3), bases[faces]).transpose(0, 2, 1, 3).reshape(len(faces), 3, 6)
    return J, (2 * faces[:, :, None] + np.arange(2)).reshape(len(faces), 6)


def _gradient(J, unknowns, residual, n):
    """J^T r, (2n,)."""
    return np.bincount(unknowns.ravel(), weights=np.einsum("tri,tr->ti", J, residual).ravel(),
                       minlength=2 * n)


def vertex_ordering(faces, n):
    """Reverse Cuthill-McKee order of the vertices along the mesh edges.

    SuperLU's minimum-degree ordering is fast and fills little when started from a spatially
    coherent order, and very slow from some (36 s instead of 2 s on a 41k-vertex icosphere).
    """
    return reverse_cuthill_mckee(vertex_graph(faces, n), symmetric_mode=True)


# From this many vertices the normal matrix is ordered by METIS nested dissection of the mesh graph
# (both unknowns of a vertex together), below it by SuperLU's minimum degree after reverse
# Cuthill-McKee: nested dissection fills less and factorises faster on large meshes (random hulls:
# 1.1x at 20k vertices, 1.5x at 43k, 1.8x at 80k; the Loop armadillo, 173k: 1.5x; ordering included),
# and is no faster below ~10k (0.8-1.0x, under 0.1 s either way).
NESTED_DISSECTION_VERTICES = 10_000


def unknown_ordering(faces, n, vertex_order=None):
    """Fill-reducing order of the 2n unknowns for the normal matrix, and SuperLU's ``permc_spec``.

    The vertex order (:func:`sparse_lu.nested_dissection` or :func:`vertex_ordering`) with a vertex's
    two unknowns adjacent; ordering the mesh graph rather than the matrix's (4x the edges) costs half
    as much for the same fill. ``vertex_order`` (the n vertices in a nested-dissection order, e.g.
    ``Connectivity.vertex_order`` restricted to them) is used instead of ordering from scratch from
    NESTED_DISSECTION_VERTICES vertices.
    """
    if n >= NESTED_DISSECTION_VERTICES and vertex_order is not None:
        order, permc_spec = vertex_order, "NATURAL"
    elif n >= NESTED_DISSECTION_VERTICES:
        order, permc_spec = sparse_lu.nested_dissection(vertex_graph(faces, n)), "NATURAL"
    else:
        order, permc_spec = vertex_ordering(faces, n), "MMD_AT_PLUS_A"
    return (2 * np.asarray(order)[:, None] + np.arange(2)).ravel(), permc_spec


def _used_order(vertex_order, used):
    """``vertex_order`` (all vertices) restricted to the sorted vertex subset ``used``, in local indices."""
    keep = np.zeros(len(vertex_order), bool)
    keep[used] = True
    return sparse_lu.restricted_order(vertex_order, keep, minimum=0)


def _vertex_pairs(faces, n):
    """The vertex pairs (column * n + row, sorted) of the normal matrix's 2x2 blocks, and the pair of
    every entry (f, k, l) of the faces' 3x3 blocks (row vertex faces[f, k], column faces[f, l]),
    flattened: ``np.unique(column * n + row, return_inverse=True)`` of the 9t entries, computed
    from the 3t face sides instead (the n diagonal pairs and both directions of each edge), which
    sorts a third as many keys (1.0 s instead of 2.5 s at 692k vertices).
    """
    t = len(faces)
    faces = np.asarray(faces, np.int64)
    a, b = faces, faces[:, [1, 2, 0]]                                  # side s joins corners s and s + 1
    edges, edge_of_side = np.unique((np.minimum(a, b) * n + np.maximum(a, b)).ravel(), return_inverse=True)
    edge_of_side = edge_of_side.reshape(t, 3)
    m = len(edges)
    low, high = np.divmod(edges, n)
    keys = np.concatenate([np.arange(n, dtype=np.int64) * (n + 1), edges, high * n + low])
    order = np.argsort(keys)
    rank = np.empty(len(keys), np.int64)
    rank[order] = np.arange(len(keys))
    which = np.empty((t, 3, 3), np.int64)
    side = np.array([[-1, 0, 2], [0, -1, 1], [2, 1, -1]])              # the side joining corners k and l
    for k in range(3):
        which[:, k, k] = rank[faces[:, k]]
        for col in range(3):
            if col != k:
                # key column * n + row is the edge's (low, high) key when the column is the lower vertex
                which[:, k, col] = rank[n + edge_of_side[:, side[k, col]] + m * (faces[:, col] > faces[:, k])]
    return keys[order], which.ravel()


def normal_matrix(J, faces, n, damping):
    """J^T J + damping * diag(J^T J) + 1e-12 * mean(diag(J^T J)) as a CSC matrix over the 2n unknowns.

    Summed from the faces' 6x6 blocks per pair of vertices (the pattern is the mesh graph's, in 2x2
    blocks), and laid out directly in CSC order: about half the time of scipy summing the 36 entries
    per face as COO duplicates (0.6 s instead of 1.1 s at 173k vertices).
    """
    t = len(faces)
    # blocks[f, k, l] is the 2x2 block of rows of vertex faces[f, k] and columns of faces[f, l].
    blocks = np.einsum("tri,trj->tij", J, J).reshape(t, 3, 2, 3, 2).transpose(0, 1, 3, 2, 4).reshape(9 * t, 2, 2)
    pairs, which = _vertex_pairs(faces, n)                             # sorted by column, then row
    q, p = np.divmod(pairs, n)
    count = np.bincount(q, minlength=n)                                # vertex pairs in column vertex q
    first = np.cumsum(count) - count
    rank = np.arange(len(pairs)) - first[q]
    indptr = np.r_[0, np.cumsum(np.repeat(2 * count, 2))]
    indices = np.empty(4 * len(pairs), np.int64)
    data = np.empty(4 * len(pairs))
    diagonal = np.flatnonzero(p == q)                                  # one pair per vertex, in order
    diag_at = np.empty((n, 2), np.int64)
    for a in range(2):
        for b in range(2):
            # Column 2q + b holds, for each row vertex p in order, rows 2p and 2p + 1.
            at = 4 * first[q] + b * 2 * count[q] + 2 * rank + a
            indices[at] = 2 * p + a
            data[at] = np.bincount(which, weights=blocks[:, a, b], minlength=len(pairs))
            if a == b:
                diag_at[:, a] = at[diagonal]
    diag = data[diag_at.ravel()]
    data[diag_at.ravel()] += damping * diag + 1e-12 * diag.mean()
    return sp.csc_matrix((data, indices, indptr), shape=(2 * n, 2 * n))


class _NormalMatrixFactor:
    """Sparse LU of the normal matrix (:func:`normal_matrix`).

    The matrix is symmetric positive definite, so SuperLU runs in symmetric mode without row
    pivoting, on ``ordering`` (:func:`unknown_ordering`). A tiny absolute term keeps the three
    rotations (the null space) nonsingular; the gradient has no component along them, so they do
    not move.
    """

    def __init__(self, J, faces, n, damping, ordering):
        perm, permc_spec = ordering
        self.lu = sparse_lu.factorize(normal_matrix(J, faces, n, damping), ordering=perm, permc_spec=permc_spec,
                                      diag_pivot_thresh=0.0, options=dict(SymmetricMode=True))
        self.solve = self.lu.solve


def angle_errors(positions, faces, angles):
    """Max and RMS |angle measured from positions - solved angle| (radians)."""
    err = spherical_angles(positions, faces) - angles
    err = np.where(np.isfinite(err), err, np.inf)
    return float(np.abs(err).max()), float(np.sqrt(np.mean(err ** 2)))


def chord_mismatch(positions, edges, chords):
    """Max relative |chord from positions - chord from the solved angles| over the edges."""
    measured = np.linalg.norm(positions[edges[:, 0]] - positions[edges[:, 1]], axis=1)
    return float(np.max(np.abs(measured - chords) / chords))


# A freshly linearised step that gains less than half but more than SLOW_PROGRESS of the sum of
# squares is slow progress, not the rounding floor, while the largest residual is above SLOW_TARGET
# (ten times below the 1e-6 the pipeline promises): on armadillo.obj's equal-areas map (~3,000 corners
# under 1 deg or over 170 deg) each such step gains 15-20%, and stopping at the first one left
# 1.4e-5 rad; 36 more reach 1e-6 (2 s each at 86k triangles). SLOW_TARGET is 1e-8, just above the
# rounding floor of meshes with tiny triangles (~3e-9 on a 50k random hull), since steps that reuse a
# factorisation are cheap (the Loop armadillo: 1.2e-8 after one step, 8.6e-9 after three).
SLOW_PROGRESS = 0.05
SLOW_TARGET = 1e-8

# After the first step, each step solves the normal equations at the current positions by conjugate
# gradients preconditioned with the last factorisation, which stays an excellent preconditioner
# while the positions move little (1-3 iterations after a walk without repairs). A step whose
# conjugate gradients do not reach a relative residual of REUSE_TOLERANCE within REUSE_ITERATIONS
# iterations is still taken (it reduces the linear model more than the reused factorisation's own
# step), and if it gains less than tenfold the normal matrix is factorised afresh. A factorisation
# costs 30-50 back-substitutions (3.3 s at 173k vertices; 5 s before nested dissection) and was the
# unfold's main cost: the simplified Gauss-Newton this replaces refactorised whenever a reused
# factorisation gained less than tenfold, which near the rounding floor it always does.
REUSE_ITERATIONS = 8
REUSE_TOLERANCE = 1e-6


def _normal_operator(J, unknowns, n, damping):
    """x -> (J^T J + damping diag(J^T J) + the factorisation's absolute term) x, from the blocks."""
    diag = np.bincount(unknowns.ravel(), weights=np.einsum("tri,tri->ti", J, J).ravel(), minlength=2 * n)
    shift = damping * diag + 1e-12 * diag.mean()

    def apply(x):
        Jx = np.einsum("tri,ti->tr", J, x[unknowns])
        return np.bincount(unknowns.ravel(), weights=np.einsum("tri,tr->ti", J, Jx).ravel(),
                           minlength=2 * n) + shift * x
    return apply


def _preconditioned_cg(apply, precondition, rhs, tolerance, max_iterations):
    """Conjugate gradients for apply(x) = rhs from 0: (x, iterations, converged).

    Not converged, x is the last iterate (None if the first direction had no positive curvature).
    """
    x = np.zeros_like(rhs)
    residual = rhs.copy()
    goal = tolerance * np.linalg.norm(rhs)
    z = precondition(residual)
    direction = z.copy()
    rz = residual @ z
    for iteration in range(1, max_iterations + 1):
        image = apply(direction)
        curvature = direction @ image
        if not (np.isfinite(curvature) and curvature > 0):
            return (x if iteration > 1 else None), iteration, False
        alpha = rz / curvature
        x += alpha * direction
        residual -= alpha * image
        if np.linalg.norm(residual) <= goal:
            return x, iteration, True
        z = precondition(residual)
        rz, previous = residual @ z, rz
        direction = z + (rz / previous) * direction
    return x, max_iterations, False


def _residual_stats(r):
    """Max and RMS of angle residuals, non-finite ones counted as inf."""
    r = np.where(np.isfinite(r), r, np.inf)
    return float(np.abs(r).max(initial=0.0)), float(np.sqrt(np.mean(r ** 2))) if r.size else 0.0


def correct(faces, angles, positions, max_iterations=100, tolerance=1e-13, slow_target=SLOW_TARGET,
            vertex_order=None):
    """Gauss-Newton on all corner-angle residuals, positions kept on the unit sphere.

    Each vertex moves in its tangent plane and is retracted by normalising. Every step is a
    Gauss-Newton step at the current positions: the first solves the normal equations with a sparse
    factorisation, the next ones by conjugate gradients preconditioned with it (a few iterations
    while the positions have moved little since), and the normal matrix is factorised afresh only
    when that stops converging quickly, with more Levenberg-Marquardt damping when a step fails.
    It stops when the largest residual is below ``tolerance``, or a step no longer halves the sum
    of squares while the largest residual is below ``slow_target`` or the step gained less than
    :data:`SLOW_PROGRESS` of it, which is where rounding in the angles themselves (largest on tiny
    and sliver triangles) sets the floor; needle-rich maps converge linearly above it and keep going.

    Parameters
    ----------
    faces : (t, 3) int array
        The triangles to fit (all of them, or those the walk has completed so far); only their
        vertices move.
    angles : (t, 3) array
        Solved angles of these triangles.
    positions : (n, 3) array
        Starting positions (the walk's).
    max_iterations : int
        Most steps (each one residual, one gradient, one solve).
    tolerance : float
        Largest angle residual (radians) that counts as converged.
    slow_target : float
        Above this largest residual, slow but steady progress (see :data:`SLOW_PROGRESS`) goes on;
        ``np.inf`` stops at the first step that does not halve the sum of squares.
    vertex_order : (n_all,) int array, optional
        A nested-dissection order of all vertices (``Connectivity.vertex_order``), restricted to the
        vertices of ``faces`` for the factorisation instead of ordering them afresh.

    Returns
    -------
    positions : (n, 3) array of unit vectors
    stats : dict
        ``iterations``, ``factorizations``, ``cg_iterations`` (preconditioned conjugate-gradient
        iterations of the steps that reused a factorisation), ``start_max_angle_error``,
        ``start_rms_angle_error``, ``max_angle_error``, ``rms_angle_error`` (radians, over these
        triangles, before and after).

    Examples
    --------
    >>> from sphere_nlp.shapes import icosphere
    >>> V, F = icosphere(2)
    >>> rng = np.random.default_rng(0)
    >>> nudged = V + 1e-4 * rng.normal(size=V.shape)
    >>> X, stats = correct(F, spherical_angles(V, F), nudged)
    >>> float(np.abs(spherical_angles(X, F) - spherical_angles(V, F)).max()) < 1e-12
    True
    """
    used, F = np.unique(np.asarray(faces), return_inverse=True)
    F = F.reshape(-1, 3)
    n = len(used)
    A = np.asarray(angles, float)
    X = _unit(np.asarray(positions, float)[used])
    r = spherical_angles(X, F) - A
    stats = dict(zip(("start_max_angle_error", "start_rms_angle_error"), _residual_stats(r)))
    cost = float(np.sum(r * r))
    damping = 1e-10
    lu = bases = None
    ordering = None                   # computed at the first factorisation
    iterations = factorizations = cg_iterations = 0
    while iterations < max_iterations and np.abs(r).max() > tolerance:
        if lu is None:
            bases = tangent_bases(X)
            J, unknowns = _angle_jacobian(X, F, bases)
            if ordering is None:
                ordering = unknown_ordering(F, n, None if vertex_order is None else
                                            _used_order(vertex_order, used))
            try:
                lu = _NormalMatrixFactor(J, F, n, damping, ordering)
            except RuntimeError:      # numerically singular: damp harder
                damping *= 100
                if damping > 1e4:
                    break
                lu = None
                continue
            factorizations += 1
            step, exact = -lu.solve(_gradient(J, unknowns, r, n)), True
        else:
            # The retraction's Jacobian at the current positions, in the tangent bases of the last
            # factorisation (an exact linearisation: only the coordinates are those of its bases).
            J, unknowns = _angle_jacobian(X, F, bases)
            step, used_iterations, exact = _preconditioned_cg(
                _normal_operator(J, unknowns, n, damping), lu.solve, -_gradient(J, unknowns, r, n),
                REUSE_TOLERANCE, REUSE_ITERATIONS)
            cg_iterations += used_iterations
            if step is None:          # no usable direction: factorise afresh
                lu = None
                continue
        trial = _unit(X + np.einsum("nxd,nd->nx", bases, step.reshape(n, 2)))
        r_trial = spherical_angles(trial, F) - A
        cost_trial = float(np.sum(r_trial * r_trial))
        iterations += 1
        if cost_trial < cost:
            X, r, cost_before, cost = trial, r_trial, cost, cost_trial
            if not exact:
                if cost > 0.1 * cost_before:
                    lu = None         # the reused factorisation has gone stale
                continue
            if cost > 0.5 * cost_before and (np.abs(r).max() <= slow_target
                                             or cost > (1 - SLOW_PROGRESS) * cost_before):
                break                 # at the rounding floor
            continue
        if not exact:
            lu = None
            continue
        if cost_trial < 4 * cost or damping > 1e4:
            break                     # a rounding-level wobble, or no step helps: stop here
        damping *= 100                # the linear model is not trusted this far: shorten the step
        lu = None
    out = np.array(positions, float)
    out[used] = X
    stats.update(iterations=iterations, factorizations=factorizations, cg_iterations=cg_iterations)
    stats["max_angle_error"], stats["rms_angle_error"] = _residual_stats(r)
    return out, stats


def unfold(connectivity, angles, seed_face=None, average=True, correction=True, excess=None):
    """Vertex positions on the unit sphere that realise the solved angles.

    Parameters
    ----------
    connectivity : Connectivity
    angles : (t, 3) array
        Solved spherical angles (they must satisfy (6)-(8)).
    seed_face : int, optional
        First triangle to place; default :func:`central_face` among well-shaped faces with reliable
        chords.
    average : bool
        Average the walk's placements of a vertex over the triangles that reach it (default), or use
        the best-conditioned triangle only.
    correction : bool
        Run the Gauss-Newton correction after the walk, and the walk's own repairs (default).
    excess : (t,) array, optional
        Solved excesses; more accurate than recomputing them from the angles for tiny triangles.

    Returns
    -------
    positions : (n, 3) array of unit vectors
    info : dict
        ``seed_face``; ``levels`` (breadth-first levels walked); ``walk_repairs`` (corrections run
        during the walk, 0 on well-shaped meshes); ``edge_chord_mismatch`` (largest relative
        disagreement of an edge's chord between its two triangles); for the walk's positions
        (``walk_*``, before the final correction) and the returned ones (``corrected_*``):
        ``max_angle_error`` and ``rms_angle_error`` (radians, against the solved angles) and
        ``max_chord_mismatch`` (relative, against the chords of the solved angles, which for tiny
        triangles are themselves uncertain); ``correction_iterations``,
        ``correction_factorizations``, ``correction_cg_iterations`` (see :func:`correct`);
        ``walk_s``, ``correction_s`` (seconds).

    Examples
    --------
    >>> from sphere_nlp.shapes import icosphere
    >>> from sphere_nlp.connectivity import build_connectivity
    >>> from sphere_nlp.certify import spherical_angles
    >>> V, F = icosphere(2)
    >>> X, info = unfold(build_connectivity(F, len(V)), spherical_angles(V, F))
    >>> info["corrected_max_angle_error"] < 1e-12
    True
    """
    F = connectivity.faces
    A = np.asarray(angles, float)
    chords, mismatch = edge_chords(connectivity, A, excess)
    if seed_face is None:
        # The seed's chords set the scale of the whole walk: take a well-shaped, reliable one.
        reliable = _edge_mismatch(connectivity, A, excess)[corner_edges(connectivity)].reshape(-1, 3).max(1) \
            <= RELIABLE_CHORD_MISMATCH
        seed = central_face(connectivity, reliable & (np.sin(A).min(1) >= WELL_CONDITIONED_SIN))
    else:
        seed = int(seed_face)
    # One order for the walk's repairs and the final correction (none for the walk alone): the whole
    # mesh's order restricted to a part keeps its separators, so it orders the part about as well as
    # a METIS call of its own would. Counted in the correction's time.
    clock = time.perf_counter()
    vertex_order = (connectivity.vertex_order()
                    if correction and connectivity.n_vertices >= NESTED_DISSECTION_VERTICES else None)
    ordering_s = time.perf_counter() - clock
    clock = time.perf_counter()
    positions, levels, repairs = walk(connectivity, A, seed, chords=chords, average=average,
                                      repair=correction, excess=excess, vertex_order=vertex_order)
    info = {"seed_face": seed, "levels": levels, "walk_repairs": repairs, "edge_chord_mismatch": mismatch,
            "walk_s": time.perf_counter() - clock}
    info["walk_max_chord_mismatch"] = chord_mismatch(positions, connectivity.edges, chords)
    if not correction:
        info["walk_max_angle_error"], info["walk_rms_angle_error"] = angle_errors(positions, F, A)
    else:
        clock = time.perf_counter()
        positions, stats = correct(F, A, positions, vertex_order=vertex_order)
        info["correction_s"] = time.perf_counter() - clock + ordering_s
        info["correction_iterations"] = stats["iterations"]
        info["correction_factorizations"] = stats["factorizations"]
        info["correction_cg_iterations"] = stats["cg_iterations"]
        # correct() measured both over every face (a closed mesh's faces use every vertex).
        info["walk_max_angle_error"] = stats["start_max_angle_error"]
        info["walk_rms_angle_error"] = stats["start_rms_angle_error"]
        info["corrected_max_angle_error"] = stats["max_angle_error"]
        info["corrected_rms_angle_error"] = stats["rms_angle_error"]
        info["corrected_max_chord_mismatch"] = chord_mismatch(positions, connectivity.edges, chords)
    return positions, info


def sphere_positions(connectivity, angles, excess):
    """Unit-sphere positions unfolded from solved angles, and the unfold statistics.

    All NaN (and no statistics) when the angles cannot be unfolded (non-finite or non-positive),
    so that the certificate reports the failure.

    Examples
    --------
    >>> from sphere_nlp.shapes import octahedron
    >>> from sphere_nlp.connectivity import build_connectivity
    >>> V, F = octahedron()
    >>> X, _ = sphere_positions(build_connectivity(F, 6), np.full((8, 3), np.pi / 2), np.full(8, np.pi / 2))
    >>> bool(np.allclose(np.linalg.norm(X, axis=1), 1))
    True
    """
    if not (np.isfinite(angles).all() and (angles > 0).all()):
        return np.full((connectivity.n_vertices, 3), np.nan), {}
    # The walk's and the correction's temporaries (tens of MB each, made anew every step) stay on
    # the heap instead of faulting in fresh pages each time (sphere_nlp.heap).
    with arrays_on_heap():
        positions, unfold_info = unfold(connectivity, angles, excess=excess)
    return positions / np.linalg.norm(positions, axis=1, keepdims=True), unfold_info
