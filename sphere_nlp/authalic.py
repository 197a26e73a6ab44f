"""The fast authalic stage of the area modes: a bijective near-area-preserving map before the NLP.

Two steps, both on vertex positions (plain numpy and scipy.sparse):

1. :func:`stretch_energy_map`: stretch-energy minimisation (SEM; Yueh, Lin, Wu & Yau, J. Sci.
   Comput. 78, 2019), a fixed-point iteration of Laplacian solves whose edge weights are the image's
   cotangents times its area stretch. One sparse solve per step moves area across the whole sphere
   at once, which is what a conformal start needs: its limbs are shrunk by factors of e^10 and more,
   far beyond what any local step could undo.
2. :func:`authalic_descent`: Riemannian L-BFGS on the product of spheres (S^2)^n (after Sutti &
   Yueh, 2024, who use Barzilai-Borwein gradient descent) of the energy
   ``mean((log(Omega_t / e'_t))^2)``, where ``Omega_t`` is the solid angle (spherical area) of
   triangle t and ``e'_t`` its target area. The logarithm is a barrier: a step that would make any
   triangle's solid angle non-positive is shortened, so every iterate is a certified map.

:func:`authalic_map` runs both; every map it returns is certified.

Examples
--------
>>> from sphere_nlp.shapes import cylinder
>>> from sphere_nlp.connectivity import build_connectivity
>>> from sphere_nlp.geometry import triangle_areas
>>> from sphere_nlp.starts import starting_positions
>>> V, F = cylinder()
>>> start, _ = starting_positions(build_connectivity(F, len(V)), V)
>>> target = triangle_areas(V, F) * (4 * np.pi / triangle_areas(V, F).sum())
>>> result = authalic_map(V, F, start, target)
>>> certify(result.positions, F).valid, result.mean_abs_log_area < 0.1 * result.start_mean_abs_log_area
(True, True)
"""

import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from . import interrupts, sparse_lu
from .certify import certify
from .conformal import _assemble_edge_weights, _inverse_stereographic
from .connectivity import vertex_graph
from .geometry import cross, rotation_between, signed_solid_angles, triangle_areas
from .untangle import untangle


def mean_abs_log_area(positions, faces, target_excess):
    """mean |log(spherical area / target area)| over the triangles (inf if any is not positive)."""
    omega = signed_solid_angles(positions, faces)
    if not (omega > 0).all():
        return float("inf")
    return float(np.mean(np.abs(np.log(omega / target_excess))))


# --- stretch-energy minimisation ----------------------------------------------------------------------

def _stereographic(positions):
    """Plane points (n, 2) of unit vectors, projected from the north pole (inverse of
    ``conformal._inverse_stereographic``)."""
    return positions[:, :2] / (1 - positions[:, 2])[:, None]


def stretch_laplacian(positions, faces, target_share):
    """The stretch Laplacian L_S(f) of the sphere map ``positions``, (n, n) sparse.

    Edge weights are the cotangents of the image's chord triangles times each triangle's stretch
    (its share of the image area over its share of the target), as in Yueh et al. (2019); x^T L x is
    then the stretch energy of x, and L_S(f) f = 0 on the free vertices at an area-preserving f.
    The cotangent's denominator (twice the image triangle's area) cancels against the stretch's
    numerator, so a weight is the corner's dot product over the image's total area and the target
    share: finite where an image triangle has collapsed to zero area (a thin limb's tip).
    """
    corners = positions[faces]
    to_next = np.roll(corners, -1, axis=1) - corners
    to_prev = np.roll(corners, 1, axis=1) - corners
    twice_total = np.linalg.norm(cross(to_next[:, 0], to_prev[:, 0]), axis=1).sum()
    dot = np.einsum("tjk,tjk->tj", to_next, to_prev)
    return _assemble_edge_weights(faces, 0.5 * dot / (twice_total * target_share)[:, None], len(positions))


def stretch_energy_map(positions, faces, target_excess, max_steps=50, radius=1.3, patience=3, deadline=None,
                       progress=None, vertex_order=None):
    """Stretch-energy minimisation from a bijective sphere map; the positions after it, (n, 3).

    Each step inverts the stereographic plane (so that the other hemisphere is inside), solves the
    stretch Laplacian for the vertices within ``radius`` of the origin with the rest fixed, and
    lifts the plane back to the sphere. It returns the step of least stretch energy, stopping when
    ``patience`` steps in a row found none lower (the first steps from a conformal map whose limbs
    are shrunk by e^-10 can raise it before they lower it: koala.obj), after ``max_steps``, or at
    ``deadline`` (a ``time.perf_counter`` value). The SEM step is not orientation-safe (a few
    triangles can flip), so it also returns the least-energy step that is a bijective map (None if
    none is): (least energy, least energy among the bijective). ``progress(stage, step, energy,
    0.0, seconds)`` is called after each step. ``vertex_order``: the mesh's nested-dissection order,
    restricted to each step's unknowns (:func:`sphere_nlp.sparse_lu.restricted_order`).
    """
    faces = np.asarray(faces, dtype=np.int64)
    target_share = target_excess / target_excess.sum()
    S = np.asarray(positions, dtype=float)
    # Rotate so that no vertex sits at the north pole, which the projection sends to infinity.
    pole = S[np.argmax(S[:, 2])]
    if pole[2] > 1 - 1e-6:
        S = S @ rotation_between(pole, np.array([0.0, -np.sqrt(0.5), np.sqrt(0.5)])).T
    orientation = np.sign(signed_solid_angles(S, faces).sum())

    def energy(X):
        L = stretch_laplacian(X, faces, target_share)
        return float(np.einsum("ij,ij->", X, L @ X)) / 2, L

    E, L = energy(S)
    best, best_energy, since_best = S, E, 0
    bijective, bijective_energy = None, np.inf
    plane = _stereographic(S)
    began = time.perf_counter()
    for step in range(1, max_steps + 1):
        if deadline is not None and time.perf_counter() > deadline or since_best >= patience:
            break
        interrupts.raise_if_interrupted()
        plane = plane / np.einsum("ij,ij->i", plane, plane)[:, None]      # z -> 1 / conj(z)
        inner = np.linalg.norm(plane, axis=1) < radius
        if inner.all() or not inner.any():
            break
        rhs = -(L[inner][:, ~inner] @ plane[~inner])
        try:
            plane[inner] = sparse_lu.solve(L[inner][:, inner], np.asarray(rhs),
                                           ordering=sparse_lu.restricted_order(vertex_order, inner))
        except RuntimeError:                 # singular or not finite: the weights degenerated
            break
        plane /= np.median(np.linalg.norm(plane, axis=1))
        S = _inverse_stereographic(plane)
        # The inversion is orientation-reversing on the sphere; mirror to keep the faces' orientation.
        if np.sign(signed_solid_angles(S, faces).sum()) != orientation:
            plane[:, 0] = -plane[:, 0]
            S = _inverse_stereographic(plane)
        if not np.isfinite(S).all():
            break
        E, L = energy(S)
        since_best += 1
        if E < best_energy:
            best, best_energy, since_best = S, E, 0
        if E < bijective_energy and certify(S, faces).valid:
            bijective, bijective_energy = S, E
        if progress is not None:
            progress("authalic SEM", step, E, 0.0, time.perf_counter() - began)
    return best, bijective


# --- Riemannian descent ---------------------------------------------------------------------------------

def _dot(a, b):
    # einsum, not BLAS: a threaded BLAS dot on vectors this size is slower than one core's loop,
    # and far slower when other processes hold the cores.
    return float(np.einsum("i,i->", a, b))


def _area_penalty(r):
    """phi(r) and phi'(r) of a log area ratio r: (e^r - 1)^2 above the target, as (9) charges it,
    r^2 below it, a barrier as the triangle shrinks to nothing (the two agree to second order at 0)."""
    grow = np.expm1(np.maximum(r, 0))
    value = np.where(r > 0, grow * grow, r * r)
    slope = np.where(r > 0, 2 * grow * (grow + 1), 2 * r)
    return value, slope


class AuthalicEnergy:
    """The relative area error with a barrier, over unit positions, and its gradient.

    ``E = sum_t phi(log(Omega_t / e'_t))``: every triangle's relative error counts alike, as in the
    mean |log area ratio| the area modes promise; below a target ``phi`` is the squared logarithm,
    which keeps every triangle positively oriented (:func:`_area_penalty`). Weighing the triangles
    by (e'_t / e_mean)^2, as (9)'s area term does, leaves a body's small triangles (fingers, claws)
    nearly free, and the descent then trades their error for the large ones' (human_woman.obj: the
    mean error rose from SEM's 0.24 to 0.34; uniform: 0.024 after 130 steps).
    The angle term of (9) is left to the NLP polish: a first-order method converges slowly on it.
    """

    def __init__(self, faces, target_excess, n_vertices):
        self.faces = np.asarray(faces, dtype=np.int64)
        self.log_target = np.log(target_excess)
        self.n = n_vertices

    def log_ratio(self, X):
        """log(Omega_t / e'_t), or None if some triangle is not positively oriented or the map's
        degree is not 1 (sum of solid angles other than 4 pi)."""
        omega = signed_solid_angles(X, self.faces)
        if not (omega > 0).all() or abs(omega.sum() - 4 * np.pi) > 1e-6:
            return None
        return np.log(omega) - self.log_target

    def value(self, X):
        """(E, log ratios); E = inf and None where X is not a valid map."""
        r = self.log_ratio(X)
        if r is None:
            return np.inf, None
        return float(np.sum(_area_penalty(r)[0])), r

    def gradient(self, X, r):
        """Riemannian gradient of E at X: its ambient gradient projected onto the tangent planes."""
        f = self.faces
        P = X[f]
        a, b, c = P[:, 0], P[:, 1], P[:, 2]
        # Omega = 2 atan2(N, D), N = det[a, b, c], D = 1 + a.b + b.c + c.a (Van Oosterom & Strackee),
        # so dOmega = 2 (D dN - N dD) / (N^2 + D^2), with dN/da = b x c and dD/da = b + c.
        N = np.einsum("ij,ij->i", a, cross(b - a, c - a))
        D = 1 + np.einsum("ij,ij->i", a, b) + np.einsum("ij,ij->i", b, c) + np.einsum("ij,ij->i", c, a)
        omega = np.exp(r + self.log_target)
        scale = (_area_penalty(r)[1] / omega) * 2 / (N * N + D * D)
        sD, sN = (scale * D)[:, None], (scale * N)[:, None]
        grad = np.stack([sD * cross(b, c) - sN * (b + c),
                         sD * cross(c, a) - sN * (c + a),
                         sD * cross(a, b) - sN * (a + b)], axis=1)
        G = np.empty_like(X)
        for k in range(3):
            G[:, k] = np.bincount(f.ravel(), grad[:, :, k].ravel(), self.n)
        return G - np.einsum("ij,ij->i", G, X)[:, None] * X


class _Preconditioner:
    """A sparse model of the energy's Hessian, factorised, to precondition the descent.

    A triangle's term phi(log(Omega_t / e'_t)) has curvature about 2 / Omega_t along the
    moves of its corners that change its area; a cotangent Laplacian of the current map with those
    per-triangle weights (cotangents clamped at 0.05 to keep it positive definite, plus 1e-3 of its
    diagonal) has that scale everywhere, from a limb's tip to the body. Without it the descent's
    steps are set by the smallest triangles and the large ones barely move (koala.obj: 4 times
    slower per unit of energy).
    """

    def __init__(self, X, ratio, energy, vertex_order=None):
        faces, n = energy.faces, energy.n
        corners = X[faces]
        to_next = np.roll(corners, -1, axis=1) - corners
        to_prev = np.roll(corners, 1, axis=1) - corners
        # A triangle too small for its cotangents (or its weight) in double precision makes a
        # non-finite entry, which factorize refuses (NonFiniteSystem): the descent then ends there.
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            cot = np.einsum("tjk,tjk->tj", to_next, to_prev) / np.linalg.norm(cross(to_next, to_prev), axis=2)
            weight = 0.5 * np.maximum(cot, 0.05) * (2 / np.exp(ratio + energy.log_target))[:, None]
        L = _assemble_edge_weights(faces, weight, n)
        self.factor = sparse_lu.factorize(L + 1e-3 * sp.diags(L.diagonal()),
                                          ordering=sparse_lu.restricted_order(vertex_order, np.ones(n, bool)))

    def __call__(self, v):
        n = self.factor.shape[0]
        return self.factor.solve(np.ascontiguousarray(v.reshape(n, 3))).ravel()


@dataclass
class DescentTrace:
    """Per accepted step: seconds since the descent began, energy and mean |log area ratio|."""
    seconds: list = field(default_factory=list)
    energy: list = field(default_factory=list)
    mean_abs_log_area: list = field(default_factory=list)
    stopped: str = ""


def authalic_descent(positions, faces, target_excess, deadline=None, stall=1e-3, tolerance=1e-4,
                     max_steps=None, memory=10, refactor_every=10, progress=None, aim=None, extra_steps=0,
                     vertex_order=None):
    """Riemannian L-BFGS of :class:`AuthalicEnergy` from a certified map; (positions, trace).

    Directions come from the two-loop recursion over the last ``memory`` steps (vectors in R^3n,
    projected onto the tangent planes, the usual transport on a product of spheres), its initial
    inverse Hessian a sparse model (:class:`_Preconditioner`, refactorised every
    ``refactor_every`` steps); the step is
    taken in R^3n and each vertex normalised back onto the sphere (the retraction). A step is
    halved until every solid angle is positive, their sum 4 pi, and the energy lower by Armijo's
    rule, so every iterate is a bijective map. Stops at ``deadline`` (a ``time.perf_counter``
    value), after ``max_steps``, when the mean |log area ratio| is below ``tolerance``, when the
    energy fell by less than ``stall`` of itself over the last 50 steps, or where the map has a
    triangle too small for double precision to give it an area or a preconditioner (then it
    returns the last map, or ``positions`` unchanged, with ``trace.stopped`` saying so). With
    ``aim``, a descent whose ``max_steps`` end above that mean |log area ratio| goes on while it is
    above it, for at most ``extra_steps`` more steps (``trace.stopped`` "aim" when it got there):
    a budget in steps, not seconds, that still gives a body with thin limbs what it needs.
    ``progress(stage, step, energy, 0.0, seconds)`` is called after each step. ``vertex_order``:
    the mesh's nested-dissection order, for the preconditioner's factorisations.
    """
    faces = np.asarray(faces, dtype=np.int64)
    n = len(positions)
    energy = AuthalicEnergy(faces, target_excess, n)
    X = np.asarray(positions, dtype=float)
    X = X / np.linalg.norm(X, axis=1, keepdims=True)
    trace = DescentTrace()
    E, ratio = energy.value(X)
    if not np.isfinite(E):
        # Certified, yet a triangle's solid angle rounds to zero or below: no barrier to descend.
        trace.stopped = "a triangle of the start is too small for its solid angle"
        return X, trace
    G = energy.gradient(X, ratio)
    s_list, y_list = [], []
    began = time.perf_counter()
    step_count = 0
    start_error = float(np.mean(np.abs(ratio)))
    while True:
        step_count += 1
        if max_steps is not None and step_count > max_steps:
            if aim is None or step_count > max_steps + extra_steps:
                trace.stopped = "steps"
                break
            if (trace.mean_abs_log_area[-1] if trace.mean_abs_log_area else start_error) <= aim:
                trace.stopped = "aim" if step_count > max_steps + 1 else "steps"
                break
        if deadline is not None and time.perf_counter() > deadline:
            trace.stopped = "time"
            break
        interrupts.raise_if_interrupted()
        try:
            if (step_count - 1) % refactor_every == 0:
                precondition = _Preconditioner(X, ratio, energy, vertex_order)
            found = _line_search(energy, X, E, G, _lbfgs_direction(G.ravel(), s_list, y_list, precondition))
            if found is None and s_list:
                # The memory's direction led nowhere the barrier allows: start again from the gradient.
                s_list.clear(), y_list.clear()
                found = _line_search(energy, X, E, G, _lbfgs_direction(G.ravel(), s_list, y_list, precondition))
        except RuntimeError:            # a non-finite preconditioner or direction (sparse_lu.NonFiniteSystem)
            trace.stopped = "a triangle too small for the preconditioner"
            break
        if found is None:
            trace.stopped = "no step lowers the energy"
            break
        X_new, E_new, ratio_new = found
        G_new = energy.gradient(X_new, ratio_new)
        s, y = (X_new - X).ravel(), (G_new - G).ravel()
        if _dot(s, y) > 1e-12 * np.sqrt(_dot(s, s) * _dot(y, y)):   # keep the inverse Hessian positive
            s_list.append(s), y_list.append(y)
            if len(s_list) > memory:
                s_list.pop(0), y_list.pop(0)
        X, E, ratio, G = X_new, E_new, ratio_new, G_new
        trace.seconds.append(time.perf_counter() - began)
        trace.energy.append(E)
        trace.mean_abs_log_area.append(float(np.mean(np.abs(ratio))))
        if progress is not None:
            progress("authalic descent", step_count, E, 0.0, trace.seconds[-1])
        if trace.mean_abs_log_area[-1] < tolerance:
            trace.stopped = "tolerance"
            break
        if len(trace.energy) > 50 and trace.energy[-51] - E < stall * E:
            trace.stopped = "stalled"
            break
    return X, trace


def _line_search(energy, X, E, G, h):
    """The step along -h (tangent part) that Armijo's rule and the barrier accept, halving from 1 or
    from a step of 0.1 rad: (X_new, E_new, log ratios), or None."""
    d = -h.reshape(X.shape)
    d -= np.einsum("ij,ij->i", d, X)[:, None] * X
    slope = _dot(G.ravel(), d.ravel())
    if not slope < 0:
        return None
    # At most 0.1 rad per vertex and step: a long step could jump over a flipped configuration.
    step = min(1.0, 0.1 / max(np.linalg.norm(d, axis=1).max(), 1e-300))
    for _ in range(40):
        X_new = X + step * d
        X_new /= np.linalg.norm(X_new, axis=1, keepdims=True)
        E_new, ratio_new = energy.value(X_new)
        if E_new <= E + 1e-4 * step * slope:
            return X_new, E_new, ratio_new
        step *= 0.5
    return None


def _lbfgs_direction(g, s_list, y_list, precondition):
    """The L-BFGS two-loop recursion: H g for the inverse-Hessian estimate of the stored pairs,
    starting from ``precondition`` (a function v -> H0 v) scaled by the last pair."""
    q = g.copy()
    alphas = []
    for s, y in zip(reversed(s_list), reversed(y_list)):
        alpha = _dot(s, q) / _dot(y, s)
        q -= alpha * y
        alphas.append(alpha)
    q = precondition(q)
    if s_list:
        q *= _dot(s_list[-1], y_list[-1]) / _dot(y_list[-1], precondition(y_list[-1]))
    for s, y, alpha in zip(s_list, y_list, reversed(alphas)):
        q += (alpha - _dot(y, q) / _dot(y, s)) * s
    return q


# --- the stage ------------------------------------------------------------------------------------------

@dataclass
class AuthalicMap:
    """The authalic stage's map (certified) and how it got there.

    ``mean_abs_log_area`` is against the target areas; ``sem_mean_abs_log_area`` that of the SEM
    step (inf if it did not give a bijective map, even after untangling); ``seconds`` the stage's
    wall time, ``sem_seconds`` the part spent in SEM and untangling; ``trace`` the descent's.
    """
    positions: np.ndarray
    mean_abs_log_area: float
    start_mean_abs_log_area: float
    sem_mean_abs_log_area: float
    seconds: float
    sem_seconds: float
    trace: DescentTrace

    @property
    def steps(self):
        return len(self.trace.energy)


def authalic_map(vertices, faces, start, target_excess, max_time=None, max_steps=None, tolerance=1e-4,
                 stall=1e-3, progress=None, aim=None, extra_steps=0, vertex_order=None):
    """A bijective map of the mesh whose spherical areas approach ``target_excess``.

    ``start`` is a certified map of the mesh (the conformal start); ``vertices`` the 3D positions
    (for untangling SEM's flipped triangles). Runs :func:`stretch_energy_map`, kept if it (after
    untangling) is bijective and nearer the targets, then at most ``max_steps`` steps of
    :func:`authalic_descent` from the better map (until its mean |log area ratio| is below
    ``tolerance``; up to ``extra_steps`` more while above ``aim``), within ``max_time`` seconds. The
    result is the start itself at worst. Their sparse solves are ordered by ``vertex_order``
    (``Connectivity.vertex_order``; computed from the faces if not given, on meshes of
    :data:`sphere_nlp.sparse_lu.NESTED_DISSECTION_UNKNOWNS` vertices or more).
    """
    faces = np.asarray(faces, dtype=np.int64)
    if vertex_order is None and len(start) >= sparse_lu.NESTED_DISSECTION_UNKNOWNS:
        vertex_order = sparse_lu.nested_dissection(vertex_graph(faces, len(start)))
    target_excess = np.asarray(target_excess, dtype=float)
    began = time.perf_counter()
    deadline = None if max_time is None else began + max_time
    best = np.asarray(start, dtype=float)
    start_error = best_error = mean_abs_log_area(best, faces, target_excess)
    def out_of_time():
        return deadline is not None and time.perf_counter() > deadline

    def error_of(X):
        return mean_abs_log_area(X, faces, target_excess) if X is not None and certify(X, faces).valid else np.inf

    def sem_maps(target):
        """SEM's least-energy map (untangled where it flipped triangles) and its best bijective step."""
        sem, bijective = stretch_energy_map(best, faces, target, deadline=deadline, progress=progress,
                                            vertex_order=vertex_order)
        if not certify(sem, faces).valid and not out_of_time():
            # SEM's solves are not orientation-safe: re-embed small disks around the flipped triangles.
            sem, _ = untangle(sem, faces, mesh_vertices=vertices, progress=progress)
        return [sem, bijective]

    candidates = sem_maps(target_excess)
    sem_error = error_of(candidates[0])
    if sem_error == np.inf and not out_of_time():
        # Where SEM's map cannot be untangled (human_woman.obj equal-areas: its best bijective step
        # is at 7.8), SEM towards the surface's own areas, which its start is conformal to, opens the
        # collapsed fingers (0.23 against its own areas) for the descent to take on from there.
        own = triangle_areas(vertices, faces)
        candidates += sem_maps(own * (4 * np.pi / own.sum()))
    for candidate in candidates:
        error = error_of(candidate)
        if error < best_error:
            best, best_error = candidate, error
    sem_seconds = time.perf_counter() - began
    X, trace = authalic_descent(best, faces, target_excess, deadline=deadline, max_steps=max_steps,
                                tolerance=tolerance, stall=stall, progress=progress, aim=aim,
                                extra_steps=extra_steps, vertex_order=vertex_order)
    return AuthalicMap(positions=X, mean_abs_log_area=mean_abs_log_area(X, faces, target_excess),
                       start_mean_abs_log_area=start_error, sem_mean_abs_log_area=sem_error,
                       seconds=time.perf_counter() - began, sem_seconds=sem_seconds, trace=trace)
