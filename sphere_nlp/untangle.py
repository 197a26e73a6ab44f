"""Repair a spherical map that has a few flipped triangles by local Tutte re-embedding.

The FLASH conformal map (:func:`sphere_nlp.conformal.conformal_map`) is an excellent start for the
solver, but its cotangent weights can be negative, so on some meshes a handful of triangles come out
flipped. :func:`untangle` re-embeds only the neighbourhood of those triangles and leaves every other
vertex exactly where it was:

1. **Seeds.** Triangles whose signed solid angle is <= 0 (or not finite) are bad; their vertices are
   the seeds. In round ``r`` the *free* vertices are the seeds and their ``(r - 1)``-ring.
2. **Disk regions.** Each connected group of free vertices, with all the triangles around it, is a
   region. Tutte's construction needs a topological disk, so a region with holes gets its holes
   filled (their vertices become free) and a region whose boundary touches itself at a vertex gets
   that vertex freed, until every region is a disk (Euler characteristic 1, one simple boundary loop).
3. **Tutte in the gnomonic plane.** The region is projected onto the plane tangent to the sphere at
   the mean direction of its boundary, from the centre of the sphere. That projection maps great
   circles to straight lines, so a spherical triangle is positively oriented exactly when its image is
   (for points in the open hemisphere). The boundary stays where it is; each free vertex is placed
   at the weighted mean of its neighbours (mean-value weights of the 3D mesh, which are positive, or
   uniform weights), one sparse linear solve per region; the result is projected back.
4. **Winslow fallback.** Floater's theorem guarantees a valid Tutte layout only for a convex boundary
   polygon. If some region triangle comes out flipped, the Tutte layout is untangled with the
   regularised Winslow energy of Garanzha et al., "Foldover-free maps in 50 lines of code" (ACM ToG
   2021): a conformality measure of each triangle against its 3D shape, divided by a smoothed
   determinant whose smoothing eps is driven to 0, minimised by L-BFGS with the boundary fixed. It
   finds valid layouts inside non-convex boundaries whenever one exists in practice. The 3D
   references are scaled by the map's local area ratio (measured just outside the region and
   interpolated inward), so that the optimum has the size the map has there.
5. **Check and grow.** A region's new positions are kept only if all its triangles are positive on
   the sphere. Otherwise (or if its boundary loop does not enclose it counter-clockwise, which happens
   when the valid triangles around it overlap each other) the next round retries with a one-ring
   larger region (the Winslow untangler gives up on a region once three updates of eps in a row
   leave as many triangles inverted: a region too tight for its triangles stays so).

Only free vertices move and they touch only the region's triangles, so triangles outside the regions
are unchanged and stay valid; the result is certified as a whole at the end.

Failure is reported, not raised: :func:`untangle` returns ``None`` for the positions and says why in
``info.reason`` (flips left after ``max_rounds``, or a region that grew too large for the gnomonic
projection, i.e. the map is folded over a large part of the sphere rather than locally tangled).
"""

import time
from dataclasses import dataclass, asdict

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from . import interrupts, sparse_lu
from .certify import certify, signed_solid_angles
from .geometry import corner_angles, cross

# A region's boundary must lie within arccos(0.2) ~ 78 degrees of its centre for the gnomonic
# projection: beyond that the plane coordinates blow up (and at 90 degrees they do not exist).
MIN_PROJECTION_COS = 0.2

# Rounds of hole filling / pinch freeing before a region is declared not a disk.
MAX_DISK_PASSES = 20

WEIGHT_KINDS = ("mean-value", "uniform")


@dataclass(frozen=True)
class UntangleInfo:
    """What :func:`untangle` did.

    Attributes
    ----------
    valid : bool
        The returned positions certify (:func:`sphere_nlp.certify.certify`).
    flipped_before, flipped_after : int
        Triangles with signed solid angle <= 0 (or not finite) in the input and in the result (in the
        best positions reached, when it failed).
    rounds : int
        Rounds run; round ``r`` frees the ``(r - 1)``-ring of the bad triangles' vertices.
    regions : int
        Disk regions whose re-embedding was kept, over all rounds.
    moved_vertices : int
        Vertices whose position changed.
    largest_region : int
        Most free vertices in one kept region.
    reason : str
        Empty when valid, otherwise why it failed.
    """

    valid: bool
    flipped_before: int
    flipped_after: int
    rounds: int
    regions: int
    moved_vertices: int
    largest_region: int
    reason: str = ""

    def to_dict(self):
        return asdict(self)


def mean_value_weights(mesh_vertices, faces):
    """Floater's mean-value weights of the 3D mesh as a sparse (n, n) matrix, row i = weights of i.

    ``w_ij = (tan(a/2) + tan(b/2)) / |v_i - v_j|`` with a, b the corner angles at i next to edge ij.
    Always positive (unlike cotangent weights), and a Tutte embedding with them reproduces a planar
    mesh exactly, so they keep the re-embedded region close to the shape of the 3D mesh.

    Examples
    --------
    >>> from sphere_nlp.shapes import octahedron
    >>> V, F = octahedron()
    >>> W = mean_value_weights(V, F)
    >>> W.shape, W.nnz, bool(np.allclose(W.data, 2 * np.tan(np.pi / 6) / np.sqrt(2)))
    ((6, 6), 24, True)
    """
    V = np.asarray(mesh_vertices, float)
    F = np.asarray(faces, np.int64)
    P = V[F]
    to_next = np.roll(P, -1, axis=1) - P
    to_prev = np.roll(P, 1, axis=1) - P
    len_next = np.linalg.norm(to_next, axis=2)
    len_prev = np.linalg.norm(to_prev, axis=2)
    angle = corner_angles(V, F)
    # Clip so a (nearly) straight corner gives a large but finite weight.
    half_tan = np.tan(np.clip(angle / 2, 1e-12, np.pi / 2 - 1e-6))
    rows = np.r_[F.ravel(), F.ravel()]
    cols = np.r_[np.roll(F, -1, axis=1).ravel(), np.roll(F, 1, axis=1).ravel()]
    vals = np.r_[(half_tan / len_next).ravel(), (half_tan / len_prev).ravel()]
    n = len(V)
    return sp.coo_matrix((vals, (rows, cols)), shape=(n, n)).tocsr()


def uniform_weights(faces, n_vertices):
    """Weight 1 for every edge, as a sparse (n, n) matrix."""
    F = np.asarray(faces, np.int64)
    rows, cols = F.ravel(), np.roll(F, -1, axis=1).ravel()
    W = sp.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n_vertices, n_vertices)).tocsr()
    return ((W + W.T) > 0).astype(float).tocsr()


class _MeshTables:
    """Sparse adjacency tables of a closed oriented triangle mesh, built once per call."""

    def __init__(self, faces, n_vertices):
        F = np.asarray(faces, np.int64)
        t = len(F)
        self.faces, self.n = F, n_vertices
        # Half-edge 3 f + j runs from faces[f, j] to faces[f, j + 1].
        self.he_from = F.ravel()
        self.he_to = np.roll(F, -1, axis=1).ravel()
        keys = self.he_from * n_vertices + self.he_to
        order = np.argsort(keys)
        twin_keys = self.he_to * n_vertices + self.he_from
        pos = np.clip(np.searchsorted(keys[order], twin_keys), 0, len(keys) - 1)
        found = keys[order][pos] == twin_keys
        if not found.all():
            raise ValueError("faces are not a closed, consistently oriented surface")
        self.twin_face = order[pos] // 3
        self.face_of_he = np.repeat(np.arange(t), 3)
        ones = np.ones(3 * t)
        self.vertex_faces = sp.coo_matrix((ones, (self.face_of_he, self.he_from)),
                                          shape=(t, n_vertices)).tocsr()
        self.adjacency = sp.coo_matrix((ones, (self.he_from, self.he_to)),
                                       shape=(n_vertices, n_vertices)).tocsr()
        self.dual = sp.coo_matrix((ones, (self.face_of_he, self.twin_face)), shape=(t, t)).tocsr()

    def faces_touching(self, vertex_mask):
        return np.asarray(self.vertex_faces @ vertex_mask.astype(float)).ravel() > 0

    def dilate(self, vertex_mask, rings):
        for _ in range(rings):
            vertex_mask = vertex_mask | (np.asarray(self.adjacency @ vertex_mask.astype(float)).ravel() > 0)
        return vertex_mask

    def holes_and_pinches(self, face_mask):
        """Vertices to free so that the face set ``face_mask`` (connected) becomes a disk; empty if it is."""
        he = np.flatnonzero(np.repeat(face_mask, 3))
        boundary = he[~face_mask[self.twin_face[he]]]
        region_vertices = np.unique(self.faces[face_mask])
        n_faces = int(face_mask.sum())
        euler = len(region_vertices) - (3 * n_faces + len(boundary)) // 2 + n_faces
        outgoing = np.bincount(self.he_from[boundary], minlength=self.n)
        # A boundary vertex with two outgoing boundary half-edges is where the boundary touches itself.
        pinches = np.flatnonzero(outgoing > 1)
        if euler == 1:
            # Connected, genus 0 and (without pinches) a manifold: one boundary loop, a disk.
            return pinches
        # Holes: every connected piece of the complement except the largest (the outside).
        outside = np.flatnonzero(~face_mask)
        if len(outside) == 0:
            return region_vertices
        k, labels = connected_components(self.dual[outside][:, outside], directed=False)
        holes = outside[labels != np.argmax(np.bincount(labels))]
        return np.union1d(pinches, np.unique(self.faces[holes]))


def _disk_regions(tables, free):
    """Grow the free set until each of its connected groups, with its incident faces, is a disk.

    Returns the final free mask and a list of (free vertex indices, region face mask) pairs.
    """
    for _ in range(MAX_DISK_PASSES):
        free_idx = np.flatnonzero(free)
        k, labels = connected_components(tables.adjacency[free_idx][:, free_idx], directed=False)
        regions, grown = [], False
        for label in range(k):
            group = free_idx[labels == label]
            mask = np.zeros(tables.n, bool)
            mask[group] = True
            face_mask = tables.faces_touching(mask)
            extra = tables.holes_and_pinches(face_mask)
            if len(extra):
                if free[extra].all():
                    raise _RegionError("the flipped triangles' region covers the whole sphere")
                free[extra] = True
                grown = True
            else:
                regions.append((group, face_mask))
        if not grown:
            return free, regions
    raise _RegionError("could not grow the free vertices into disk regions in %d passes" % MAX_DISK_PASSES)


class _RegionError(Exception):
    """A region cannot be re-embedded (not a disk, too large to project)."""


def _tangent_basis(normal):
    helper = np.eye(3)[np.argmin(np.abs(normal))]
    e1 = cross(normal, helper)
    e1 /= np.linalg.norm(e1)
    return e1, cross(normal, e1)


class _Reference:
    """Per-face reference triangles for the Winslow fallback: the 3D shapes, or equilateral ones."""

    def __init__(self, mesh_vertices, faces):
        if mesh_vertices is None:
            # Equilateral, unit area.
            side = np.sqrt(4 / np.sqrt(3))
            corners = np.array([[side, side / 2], [0, side * np.sqrt(3) / 2]])
            self.inverse = np.broadcast_to(np.linalg.inv(corners), (len(faces), 2, 2))
            self.areas = np.ones(len(faces))
            return
        V = np.asarray(mesh_vertices, float)
        a, b, c = (V[faces[:, k]] for k in range(3))
        ab, ac = b - a, c - a
        length = np.linalg.norm(ab, axis=1)
        along = np.einsum("ij,ij->i", ab, ac) / length
        height = np.linalg.norm(cross(ab, ac), axis=1) / length
        # Inverse of the edge matrix [[|ab|, along], [0, height]] of the triangle in its own plane.
        inverse = np.zeros((len(faces), 2, 2))
        inverse[:, 0, 0] = 1 / length
        inverse[:, 0, 1] = -along / (length * height)
        inverse[:, 1, 1] = 1 / height
        self.inverse = inverse
        self.areas = 0.5 * length * height


def _winslow_energy(plane, faces, inverse, weights, eps, shape_weight):
    """Regularised Winslow energy of planar triangles (Garanzha et al. 2021) and its gradient.

    Per triangle, with J the Jacobian from the reference triangle and D = det J:
    ``(1 - theta) |J|^2 / chi(D) + theta (D^2 + 1) / chi(D)``, ``chi(D) = (D + sqrt(eps^2 + D^2)) / 2``.
    The first term measures conformality, the second area; both blow up as D -> 0+ once eps -> 0,
    which is what pushes flipped triangles back.
    """
    P = plane[faces]
    edges = np.stack([P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]], axis=2)       # columns: the two edges
    J = edges @ inverse
    D = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
    frob = np.einsum("tij,tij->t", J, J)
    root = np.sqrt(eps * eps + D * D)
    chi = 0.5 * (D + root)
    dchi = 0.5 * (1 + D / root)
    theta = 1 - shape_weight
    f = (shape_weight * frob + theta * (D * D + 1)) / chi
    cofactor = np.stack([np.stack([J[:, 1, 1], -J[:, 1, 0]], 1), np.stack([-J[:, 0, 1], J[:, 0, 0]], 1)], 1)
    dJ = (2 * shape_weight / chi)[:, None, None] * J + \
        ((2 * theta * D - f * dchi) / chi)[:, None, None] * cofactor
    dE = weights[:, None, None] * dJ @ np.transpose(inverse, (0, 2, 1))
    corner_grads = np.stack([-dE[:, :, 0] - dE[:, :, 1], dE[:, :, 0], dE[:, :, 1]], axis=1)   # (t, 3, 2)
    n = len(plane)
    grad = np.stack([np.bincount(faces.ravel(), corner_grads[..., k].ravel(), minlength=n)
                     for k in range(2)], axis=1)
    return float(weights @ f), grad, D


def _winslow_untangle(plane, free, faces, inverse, weights, scale, max_updates=12, max_iter=200,
                      polish_iter=200, tick=None, max_stalled_updates=3):
    """Move the ``free`` rows of ``plane`` to minimise the Winslow energy with a decreasing eps.

    ``scale`` (len(free),) is each free vertex's typical edge length: the optimiser works in those
    units, because conformal maps shrink some parts by orders of magnitude. ``tick()``, if given,
    is called after every step of the optimiser (the start's progress lines). ``max_iter`` steps
    per value of eps: on a collapsed limb's tip L-BFGS's later steps cost far more than the first
    ones (line searches on a stiffening barrier), and a smaller eps sooner does better
    (docs/tuning.md, "The conformal start"). ``max_stalled_updates`` updates of eps in a row that
    leave as many triangles inverted end the attempt (None).
    Returns the new plane positions (all rows) once every determinant is positive, else None.
    """
    from scipy.optimize import minimize

    plane = plane.copy()
    shape_weight = 127 / 128            # mostly conformality, a little area (the paper's theta = 1/128)

    def energy(y, eps):
        plane[free] = y.reshape(-1, 2) * scale[:, None]
        value, grad, _ = _winslow_energy(plane, faces, inverse, weights, eps, shape_weight)
        return value, (grad[free] * scale[:, None]).ravel()

    def determinants(y):
        plane[free] = y.reshape(-1, 2) * scale[:, None]
        return _winslow_energy(plane, faces, inverse, weights, 1.0, shape_weight)[2]

    def descend(y, eps, iterations):
        with np.errstate(all="ignore"):
            return minimize(energy, y, args=(eps,), jac=True, method="L-BFGS-B",
                            options=dict(maxiter=iterations),
                            callback=None if tick is None else (lambda _: tick())).x

    y = (plane[free] / scale[:, None]).ravel()
    det = determinants(y)
    fewest, stalled = int(np.sum(det <= 0)), 0
    for _ in range(max_updates):
        lowest = det.min()
        if lowest > 0:
            break
        y = descend(y, np.sqrt(1e-12 + 0.04 * lowest ** 2), max_iter)
        if not np.isfinite(y).all():
            return None
        # A region too tight for its triangles stops losing inverted ones, and more updates of eps
        # cannot change that: the caller grows the region instead.
        det = determinants(y)
        now = int(np.sum(det <= 0))
        stalled = 0 if now < fewest else stalled + 1
        fewest = min(fewest, now)
        if stalled >= max_stalled_updates:
            return None
    else:
        if not det.min() > 0:
            return None
    # Valid now; with eps ~ 0 the energy is a barrier at D = 0, so descending further only improves
    # the triangles' shapes (the untangling phase stops at the first valid, often sliver-filled, layout).
    polished = descend(y, 1e-6, polish_iter)
    if np.isfinite(polished).all() and determinants(polished).min() > 0:
        y = polished
    plane[free] = y.reshape(-1, 2) * scale[:, None]
    return plane


def _reembed_region(positions, context, free, face_mask):
    """New positions of the free vertices of one disk region, or None if no valid one was found.

    First the Tutte embedding in the gnomonic plane; if some of its triangles are flipped (the
    boundary polygon is not convex), the Winslow untangler started from it.
    """
    faces, W = context.faces, context.weights
    region_faces = faces[face_mask]
    region_vertices = np.unique(region_faces)
    fixed = np.setdiff1d(region_vertices, free)
    normal = positions[fixed].sum(axis=0)
    if not np.isfinite(normal).all() or np.linalg.norm(normal) == 0:
        raise _RegionError("region boundary has no mean direction")
    normal /= np.linalg.norm(normal)
    cos = positions[fixed] @ normal
    if cos.min() < MIN_PROJECTION_COS:
        raise _RegionError("region too large for a gnomonic projection (boundary %.0f degrees from "
                           "its centre)" % np.degrees(np.arccos(np.clip(cos.min(), -1, 1))))
    e1, e2 = _tangent_basis(normal)
    plane_fixed = (positions[fixed] @ np.c_[e1, e2]) / cos[:, None]
    local = np.full(len(positions), -1)
    local[free] = np.arange(len(free))
    local[fixed] = len(free) + np.arange(len(fixed))
    local_faces = local[region_faces]
    # The boundary loop must enclose a positive area counter-clockwise. It may not when the valid
    # triangles outside overlap each other near the region (an immersed, not embedded, outside);
    # then no re-embedding of this region exists and only a larger one can help.
    he = np.flatnonzero(np.repeat(face_mask, 3))
    boundary = he[~face_mask[context.tables.twin_face[he]]]
    a = plane_fixed[local[context.tables.he_from[boundary]] - len(free)]
    b = plane_fixed[local[context.tables.he_to[boundary]] - len(free)]
    if np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]) <= 0:
        return None

    W_free = W[free]
    L = (sp.diags(np.asarray(W_free.sum(axis=1)).ravel()) - W_free[:, free]).tocsc()
    try:
        solve = sparse_lu.factorize(L).solve
        W_fixed = W_free[:, fixed]
        plane = np.vstack([np.column_stack([solve(W_fixed @ plane_fixed[:, k]) for k in range(2)]), plane_fixed])
    except RuntimeError:            # singular or non-finite weights (a region of collapsed triangles)
        return None

    def lift(points):
        lifted = normal + points[:len(free)] @ np.vstack([e1, e2])
        return lifted / np.linalg.norm(lifted, axis=1, keepdims=True)

    def valid(lifted):
        trial = positions.copy()
        trial[free] = lifted
        return bool((signed_solid_angles(trial, region_faces) > 0).all())

    lifted = lift(plane)
    if valid(lifted):
        return lifted
    if not context.winslow:
        return None
    # Winslow fallback. Reference triangles are scaled by the local area ratio of the map (measured
    # on the valid faces just outside the region, interpolated inward like the positions), so that
    # a conformal map of the right size is the energy's minimum.
    outside = ~face_mask & (context.solid_angles > 0)     # the valid faces around the region
    VT = context.vertex_faces_t[fixed]
    ref_area = VT @ (context.reference.areas * outside)
    map_area = VT @ (context.solid_angles * outside)
    with np.errstate(all="ignore"):
        log_ratio_fixed = np.log(map_area / ref_area) - 3 * np.log(cos)    # gnomonic magnifies by 1/cos^3
    if not np.isfinite(log_ratio_fixed).all():
        return None
    log_ratio = np.r_[solve(W_fixed @ log_ratio_fixed), log_ratio_fixed]
    face_scale = np.exp(-0.5 * log_ratio[local_faces].mean(axis=1))
    inverse = context.reference.inverse[face_mask] * face_scale[:, None, None]
    weights = context.reference.areas[face_mask] / context.reference.areas[face_mask].mean()
    vertex_length = np.exp(0.5 * log_ratio[:len(free)]) * np.sqrt(
        (context.vertex_faces_t[free] @ context.reference.areas) / context.vertex_face_count[free])
    plane = _winslow_untangle(plane, np.arange(len(free)), local_faces, inverse, weights, vertex_length,
                              tick=context.tick)
    if plane is None:
        return None
    lifted = lift(plane)
    return lifted if valid(lifted) else None


class _Context:
    """Everything a region re-embedding needs that does not change between regions."""

    def __init__(self, faces, tables, weights, reference, winslow):
        self.faces, self.tables, self.weights = faces, tables, weights
        self.reference, self.winslow = reference, winslow
        self.vertex_faces_t = tables.vertex_faces.T.tocsr()
        self.vertex_face_count = np.asarray(self.vertex_faces_t.sum(axis=1)).ravel()
        self.solid_angles = None
        self.tick = None


def untangle(positions, faces, mesh_vertices=None, max_rounds=20, weights="mean-value", winslow=True,
             progress=None):
    """Turn a spherical map with a few flipped triangles into a valid one, moving only vertices near them.

    See the module docstring for the method.

    Parameters
    ----------
    positions : (n, 3) float array
        Points on (or near: they are normalised) the unit sphere; non-finite rows are allowed and are
        treated like vertices of flipped triangles.
    faces : (t, 3) int array
        Closed, consistently oriented genus-0 triangle mesh.
    mesh_vertices : (n, 3) float array, optional
        The 3D mesh, for mean-value weights. Without it the weights are uniform.
    max_rounds : int
        Round ``r`` re-embeds the ``(r - 1)``-ring around the triangles still flipped. A thin
        tail's tip needs many rings of room; the shared meshes need one or two rounds
        (docs/tuning.md, "The conformal start").
    weights : {"mean-value", "uniform"}
        Tutte weights.
    winslow : bool
        When a region's Tutte embedding has flipped triangles, try the Winslow untangler on it
        before growing the region.
    progress : callable(stage, step, flipped, 0.0, seconds), optional
        Called with stage "start (untangle)" after every region and every Winslow step: the steps
        so far and the triangles flipped when the round began. A thin limb's collapsed tip can take
        minutes here, so a long run says where it is.

    Returns
    -------
    positions : (n, 3) float array of unit vectors, or None
        A certified map (:func:`sphere_nlp.certify.certify` valid), equal to the normalised input
        except near the flipped triangles; None if no valid map was reached (``info.reason`` says why).
        An input that already certifies is returned normalised and otherwise unchanged.
    info : UntangleInfo

    Examples
    --------
    >>> from sphere_nlp.shapes import icosphere
    >>> V, F = icosphere(2)
    >>> X = V.copy()
    >>> X[0] = -0.3 * V[0] + V[F[F[:, 0] == 0][0, 1]]   # drag vertex 0 across a neighbour
    >>> certify(X / np.linalg.norm(X, axis=1, keepdims=True), F).valid
    False
    >>> Y, info = untangle(X, F, mesh_vertices=V)
    >>> certify(Y, F).valid, info.flipped_before > 0, info.moved_vertices < 10
    (True, True, True)
    """
    if weights not in WEIGHT_KINDS:
        raise ValueError("weights must be one of %s, not %r" % (WEIGHT_KINDS, weights))
    faces = np.asarray(faces, np.int64)
    with np.errstate(all="ignore"):
        X = np.asarray(positions, float)
        X = X / np.linalg.norm(X, axis=1, keepdims=True)
    original = X.copy()
    n = len(X)
    tables = _MeshTables(faces, n)
    if weights == "mean-value" and mesh_vertices is not None:
        W = mean_value_weights(mesh_vertices, faces)
    else:
        W = uniform_weights(faces, n)
    context = _Context(faces, tables, W, _Reference(mesh_vertices, faces), winslow)

    def bad_faces(P):
        with np.errstate(all="ignore"):
            return ~(signed_solid_angles(P, faces) > 0)

    flipped_before = int(bad_faces(X).sum())
    kept, largest, reason, rounds = 0, 0, "", 0
    began, steps, flipped_now = time.perf_counter(), 0, flipped_before

    def tick():
        nonlocal steps
        steps += 1
        if progress is not None:
            progress("start (untangle)", steps, flipped_now, 0.0, time.perf_counter() - began)

    context.tick = tick
    for rounds in range(1, max_rounds + 1):
        if interrupts.deadline_passed():
            reason = "the run's time limit was reached"     # see interrupts.deadline
            break
        with np.errstate(all="ignore"):
            omega = signed_solid_angles(X, faces)
        bad = ~(omega > 0)
        flipped_now = int(bad.sum())
        # The valid faces' solid angles measure the map's local scale (for the Winslow references).
        context.solid_angles = np.where(bad, 0.0, omega)
        if not bad.any():
            rounds -= 1
            break
        seeds = np.zeros(n, bool)
        seeds[faces[bad].ravel()] = True
        # A vertex with a non-finite position cannot be a boundary vertex: free it and its faces' vertices.
        seeds[np.unique(faces[tables.faces_touching(~np.isfinite(X).all(axis=1))])] = True
        try:
            _, regions = _disk_regions(tables, tables.dilate(seeds, rounds - 1))
        except _RegionError as error:
            reason = str(error)
            break
        errors = []
        for free, face_mask in regions:
            try:
                lifted = _reembed_region(X, context, free, face_mask)
            except _RegionError as error:
                errors.append(str(error))
                continue
            if lifted is not None:
                X[free] = lifted
                kept += 1
                largest = max(largest, len(free))
            tick()
        if errors and len(errors) == len(regions):
            reason = errors[0]          # growing only makes regions larger: stop
            break
    else:
        if bad_faces(X).any():
            reason = "triangles still flipped after %d rounds" % max_rounds
    certificate = certify(X, faces)
    if not certificate.valid and not reason:
        reason = certificate.reason
    with np.errstate(invalid="ignore"):
        moved = int(np.sum(~(X == original).all(axis=1)))
    info = UntangleInfo(valid=certificate.valid, flipped_before=flipped_before,
                        flipped_after=certificate.flipped, rounds=rounds, regions=kept,
                        moved_vertices=moved, largest_region=largest, reason=reason)
    return (X if certificate.valid else None), info
