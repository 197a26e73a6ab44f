"""Solve for the spherical angles.

``log-chord`` (default): start from a valid spherical triangulation of the mesh
(:func:`sphere_nlp.starts.starting_positions`: the conformal map, repaired if needed, else the
convex embedding),
whose angles satisfy every constraint; the inequalities (3)-(5) hold by construction in that
formulation, and the three redundant vertex constraints are left out (see
:class:`sphere_nlp.nlp.LogChordNLP`). Stages:

1. Area modes only (area weight > 0): :func:`area_continuation` walks the excesses from the start's
   to the targets with a log-area objective, so that the next stage starts near its optimum; skipped
   when the start is already near the targets (:func:`start_area_distance` at most
   ``settings.area_walk_distance``: an earlier map), whose margin stage then starts with a small
   barrier.
2. "margin": IPOPT on the objective (9) and the equalities with every u = alpha - e/2 kept >= a
   margin (corners already below it at the start: >= their own size less 10%, see
   :func:`margin_restart`), inside a trust region on the log excesses (a window of
   +-``angle_mode_excess_window``, area modes +-``excess_window``, around the start); re-centred,
   warm-started and with a window twice as wide each time its result touches the window. The
   paper adds its inequalities only when the equality solution breaks them, but here they cost
   little (in log u they are simple bounds, mostly far from active) and the optimum is often at a
   degenerate triangle, which an equality stage chases towards log u = -inf (see
   docs/tuning.md, "angle_mode_excess_window", for the iterations this saves).
3. Only if that run diverged (left the solution set): "margin-resumed", the margin stage again from
   the diverged run's best iterate near the constraints (:func:`resume_diverged`), warm-started;
   if that diverges too, or there was no such iterate, "equality", the same without the margin,
   then "margin" again from its result, or from the start if that diverged too.
4. "penalty-1e+04", "penalty-1e+06", only if the left-out vertex sums did not come back: again
   from there with their penalty 100 and then 10,000 times stiffer.
5. "all-constraints", only if they still did not: from the start with all of (7).

``faithful`` and ``substituted``: staged as in section 4 of the paper:

1. A linear least-squares start: the point closest to the targets (beta, e') that satisfies the linear
   constraints (6) and (7) exactly.
2. IPOPT with the equality constraints only.
3. Only if the result has a non-positive angle or excess, or e >= 2 alpha somewhere, IPOPT again with
   the inequalities (3)-(5) added, warm-started from stage 2.

Without the caller's ``max_iter``, every log-chord run stops at a cap scaled by the mesh's size
(:func:`stage_iteration_cap`), and a margin stage stopped there is projected as with
``on_limit="project"``. At a vertex whose targets' sum is far from 2 pi with large weights (a
spike's tip), the NLP's corner targets are shifted to sum to 2 pi (:func:`summed_targets`, the
same minimiser); ``objective`` is always (9)'s with the mode's own targets.

Each stage is a function of its own (:func:`margin_stage`, :func:`equality_fallback`,
:func:`restore_dropped_sums`, :func:`all_constraints_stage`, :func:`area_continuation`,
:func:`project_onto_constraints`) over :func:`windowed_solve`; :func:`solve_angles` runs them top
down. The tuning constants are the fields of :class:`sphere_nlp.settings.SolverSettings`; its
``on_run`` sees every IPOPT run. Plain numpy in and out; CasADi stays in :mod:`sphere_nlp.nlp`.
"""

import time
from dataclasses import dataclass, field, replace
from fractions import Fraction

import numpy as np

from . import interrupts
from .nlp import DEFAULT_FORMULATION, AngleNLP, LogChordNLP, status_kind
from .errors import UsageError
from .geometry import cross
from .heap import arrays_on_heap
from .names import AREA_MODE_OF, ON_LIMIT  # noqa: F401  (ON_LIMIT: re-exported; defined there for a light --help)
from .settings import DEFAULT_SETTINGS, SolverSettings
from .starts import angles_and_excess, initial_point
from .targets import Targets

# The projection of a stage stopped by max_time (on_limit="project") may run past the run's
# deadline (interrupts.deadline) by a fifth of max_time plus 5 s.
PROJECTION_GRACE_FRACTION = 0.2
PROJECTION_GRACE_S = 5.0


@dataclass
class AngleSolution:
    """Result of the angle solve.

    Attributes
    ----------
    angles : (t, 3) array
    excess : (t,) array
    success : bool
    status : str
        IPOPT's return status of the last stage, or "Diverged" if the divergence watch stopped it
        (see :class:`~sphere_nlp.settings.SolverSettings`' ``abort_violation``).
    iterations : int
        IPOPT iterations over all stages.
    objective : float
    max_constraint_violation : float
        max |residual| of (6), (7), (8) at (angles, excess), (8) as a difference of edge cosines.
    stages : list of dict
        One entry per IPOPT run: name, status, iterations, objective, time_s, build_s.
    initial_angles, initial_excess : arrays
        The starting point.
    start : str
        Which starting point (:func:`sphere_nlp.starts.starting_positions`): "conformal",
        "conformal-untangled", "surface-conformal", "surface-conformal-untangled", "embedding",
        "embedding-uncentred", "embedding-invalid" (not a certified map: nothing is solved, status
        :data:`NO_VALID_START`) or "linear".
    start_s : float
        Seconds spent finding it (conformal map, untangling, gauge).
    converged : bool
        True when the last stage reached IPOPT's optimality tolerance. False for a failed solve, and
        for a successful one whose margin stage stopped at ``max_iter`` or ``max_time``, or at the
        size's iteration cap (:func:`stage_iteration_cap`; its stage record has ``iteration_cap``):
        its iterate projected onto the constraints (stage "projection"), feasible but not optimal;
        ``status`` is then the stopped stage's (e.g. "Maximum_WallTime_Exceeded").
    floor_corners, floor_triangles : int
        Log-chord: corners whose u end at, below or within 1% of their floor, triangles whose e end
        within 1% of theirs (:func:`floor_bounds`: ``corner_floor`` x beta, more for small targets,
        or the margin; ``area_floor`` x 4 pi / t; a triangle the start had further below keeps
        its own size as bound, ``max_floor_lift``).
    start_positions : (n, 3) array or None
        The start's positions, when the solve stopped there (status :data:`UNPLACEABLE_START`).
    """

    angles: np.ndarray
    excess: np.ndarray
    success: bool
    status: str
    iterations: int
    objective: float
    max_constraint_violation: float
    stages: list = field(default_factory=list)
    initial_angles: np.ndarray = None
    initial_excess: np.ndarray = None
    start: str = ""
    start_s: float = 0.0
    converged: bool = False
    floor_corners: int = 0
    floor_triangles: int = 0
    start_positions: np.ndarray = None


def constraint_residuals(connectivity, angles, excess):
    """Residuals of the equality constraints at (angles, excess), in the paper's form.

    (8) is the difference of the two cosines of every edge, evaluated by the half-angle form.

    Returns
    -------
    dict with arrays ``triangle`` (6) (t,), ``vertex`` (7) (n,), ``edge`` (8) (m,).
    """
    flat = np.asarray(angles, float).ravel()
    excess = np.asarray(excess, float)
    t = len(excess)
    corner = np.arange(3 * t)
    base, local = 3 * (corner // 3), corner % 3
    A, B, C = flat, flat[base + (local + 2) % 3], flat[base + (local + 1) % 3]
    # cos a by the half-angle form of the cosine rule, 1 - 2 sin(E/2) sin(A - E/2) / (sin B sin C)
    # with E the given excess (an identity when (6) holds): the quotient
    # (cos A + cos B cos C) / (sin B sin C) cancels to an absolute rounding error of ~1e-16 /
    # (sin B sin C), which exceeded the feasibility tolerance (1e-8) at a sliver with two corners at the
    # 1e-4 margin (max_planck.obj: 1.0e-8 in float64, 4.8e-11 in long double).
    half_excess = np.repeat(excess, 3) / 2
    cosines = 1 - 2 * np.sin(half_excess) * np.sin(A - half_excess) / (np.sin(B) * np.sin(C))
    c = connectivity.edge_corner_indices()
    return {
        "triangle": flat.reshape(-1, 3).sum(1) - excess - np.pi,
        "vertex": connectivity.vertex_corner_matrix() @ flat - 2 * np.pi,
        "edge": cosines[c[:, 0]] - cosines[c[:, 1]],
    }


def max_constraint_violation(connectivity, angles, excess):
    """max |residual| over (6), (7), (8); NaN-safe (NaN counts as infinite)."""
    worst = max(float(np.max(np.abs(r))) for r in constraint_residuals(connectivity, angles, excess).values())
    return worst if np.isfinite(worst) else np.inf


def violates_inequalities(angles, excess):
    """True if some angle or excess is non-positive or some e >= 2 alpha (constraints (3)-(5))."""
    return bool((angles <= 0).any() or (excess <= 0).any() or (excess[:, None] >= 2 * angles).any())


def objective_value(targets, angles, excess):
    """Objective (9) with the weights (corner weights too) and scaling of :mod:`sphere_nlp.targets`."""
    return float(targets.angle_weight * np.sum(targets.corner_weights * (angles - targets.angles) ** 2)
                 + targets.area_weight * np.sum(((excess - targets.excess) / targets.excess_scale) ** 2))


def independent_vertices(positions, degrees=None):
    """Three vertices whose positions are as close to orthonormal as the mesh allows.

    With ``degrees`` (each vertex's number of faces), only vertices of ordinary degree (at most
    twice the median, and at least 8) are chosen: a left-out sum comes back as a penalty whose
    Hessian is dense over the unknowns of the vertex's triangles, so at a vertex of degree 1,000
    it alone had 8 million nonzeros (a finely segmented cap, :func:`tests.meshgen.bipyramid`).

    Examples
    --------
    >>> P = np.array([[0, 0, 1], [1, 0, 0], [0, 1, 0], [0, 0.1, 0.99]]) / [[1], [1], [1], [0.995]]
    >>> independent_vertices(P), independent_vertices(P, degrees=np.array([1000, 3, 3, 3]))
    ([0, 1, 2], [3, 1, 2])
    """
    candidates = np.arange(len(positions))
    if degrees is not None:
        cap = max(8, 2 * float(np.median(degrees)))
        ordinary = np.flatnonzero(np.asarray(degrees) <= cap)
        candidates = ordinary if len(ordinary) >= 3 else candidates
    P = positions[candidates]
    first = int(np.argmax(P[:, 2]))
    second = int(np.argmin(np.abs(P @ P[first])))
    normal = cross(P[first], P[second])
    third = int(np.argmax(np.abs(P @ normal)))
    return [int(candidates[first]), int(candidates[second]), int(candidates[third])]


@dataclass(frozen=True)
class SummedTargets(Targets):
    """Targets whose corner targets at some vertices were shifted to sum to 2 pi
    (:func:`summed_targets`), keeping the original corner weights ``weights`` (t, 3)."""

    weights: np.ndarray = None

    @property
    def corner_weights(self):
        return self.weights


def summed_targets(connectivity, targets, vertices):
    """``targets`` with the corner targets at ``vertices`` shifted so that each vertex's sum is 2 pi,
    an equivalent objective: the same minimiser, (9) less a constant, wherever (7) holds.

    With the corner weights w_c (kept), beta'_c = beta_c + lambda / w_c, lambda = (2 pi - sum beta)
    / sum (1 / w_c) over the vertex's corners: then sum_c w_c (alpha_c - beta'_c)^2 = sum_c w_c
    (alpha_c - beta_c)^2 - 2 lambda (sum alpha - sum beta) + const, and sum alpha = 2 pi. At a
    vertex whose targets sum far from 2 pi with large weights (a spike's tip: five corners of 0.3
    degrees at weight 39,000), (9)'s gradient there is huge and balanced only by (7)'s multiplier;
    IPOPT then crawled for thousands of iterations (docs/tuning.md, "max_sum_drift"). Returns
    ``targets`` itself if ``vertices`` is empty.

    Examples
    --------
    >>> from sphere_nlp.connectivity import build_connectivity
    >>> from sphere_nlp.shapes import octahedron
    >>> from sphere_nlp.targets import make_targets
    >>> V, F = octahedron()
    >>> c = build_connectivity(F, len(V))
    >>> shifted = summed_targets(c, make_targets("original-angles", V, F, c.vertex_degree), [0])
    >>> np.degrees(shifted.angles[F == 0]).round(6).tolist(), np.degrees(shifted.angles[F == 1]).round(6).tolist()
    ([90.0, 90.0, 90.0, 90.0], [60.0, 60.0, 60.0, 60.0])
    """
    vertices = np.asarray(vertices, int)
    if vertices.size == 0:
        return targets
    faces = np.asarray(connectivity.faces).ravel()
    n = connectivity.n_vertices
    weights = np.asarray(targets.corner_weights, float)
    beta = np.asarray(targets.angles, float).ravel()
    inverse = 1.0 / weights.ravel()
    lam = (2 * np.pi - np.bincount(faces, beta, n)) / np.bincount(faces, inverse, n)
    shifted = np.zeros(n, bool)
    shifted[vertices] = True
    angles = np.where(shifted[faces], beta + lam[faces] * inverse, beta).reshape(targets.angles.shape)
    return SummedTargets(angles=angles, excess=targets.excess, angle_weight=targets.angle_weight,
                         area_weight=targets.area_weight, mode=targets.mode,
                         corner_weighting=targets.corner_weighting, weights=weights)


def dropped_sum_drift(connectivity, targets, penalty=DEFAULT_SETTINGS.dropped_penalty):
    """How far each vertex's sum (7) would drift from 2 pi if it were left out, (n,) radians.

    A left-out sum is held at 2 pi only by the penalty ``penalty`` (s - 2 pi)^2, while the angle
    term pulls it towards its targets' sum: moving the vertex's k corners together by (s - S) / k
    from their targets (S = sum of beta) costs W (s - S)^2 with W = angle weight x the sum of the
    corner weights / k^2. The minimum of the two is at W / (W + penalty) of the way from 2 pi to S:
    that, times |2 pi - S|, is the drift (a linear estimate; the other constraints resist it too).
    Nearly 0 on smooth surfaces (and exactly 0 in the equal modes, whose targets sum to 2 pi); about
    6 at the tip of a spike 30 radii long, whose five corners target 0.6 degrees each at weight 9,100.

    Examples
    --------
    >>> from sphere_nlp.connectivity import build_connectivity
    >>> from sphere_nlp.shapes import octahedron
    >>> from sphere_nlp.targets import make_targets
    >>> V, F = octahedron()
    >>> c = build_connectivity(F, len(V))
    >>> drift = dropped_sum_drift(c, make_targets("original-angles", V, F, c.vertex_degree))
    >>> round(float(drift[0]), 4)     # four 60-degree corners: 2 pi / 3 short of 2 pi, W = 1/4
    0.0052
    """
    faces = np.asarray(connectivity.faces).ravel()
    n = connectivity.n_vertices
    degree = np.maximum(np.bincount(faces, minlength=n), 1)
    weights = targets.angle_weight * np.asarray(targets.corner_weights, float).ravel()
    stiffness = np.bincount(faces, weights, n) / degree ** 2
    defect = np.abs(2 * np.pi - np.bincount(faces, np.asarray(targets.angles, float).ravel(), n))
    return stiffness / (stiffness + penalty) * defect


def solve_angles(connectivity, targets, formulation=DEFAULT_FORMULATION, ipopt_options=None,
                 max_iter=None, max_time=None, progress=None, vertices=None, start=None, on_limit="fail",
                 settings=None, corner_floor=None, area_floor=None, excess_band=None):
    """Solve the angle NLP (see the module docstring for the strategy of each formulation).

    Parameters
    ----------
    connectivity : Connectivity
    targets : Targets
    formulation : {"log-chord", "substituted", "faithful"}
    ipopt_options : dict, optional
        Extra IPOPT options, overriding ``settings.ipopt_options``.
    max_iter : int, optional
        IPOPT iteration limit per stage.
    max_time : float, optional
        Wall-clock limit in seconds per stage (the caller's whole-run limit is
        :func:`sphere_nlp.interrupts.deadline`, enforced inside every stage).
    on_limit : {"fail", "project"}
        What a log-chord margin stage stopped by ``max_iter`` or ``max_time`` yields: a failed
        solve (default), or its iterate projected onto the constraints
        (:func:`project_onto_constraints`), feasible but not optimal (``converged=False``, and
        ``status`` the stopped stage's). The paper's formulations always fail.
    progress : callable(stage, iteration, objective, violation, elapsed), optional
    vertices : (n, 3) array, optional
        3D positions (same numbering as ``connectivity``); used for the starting point.
    start : {"auto", "conformal", "embedding", "linear"} or (n, 3) array, optional
        Starting point (:func:`sphere_nlp.starts.initial_point`): the angles of a valid spherical
        triangulation (see :func:`sphere_nlp.starts.starting_positions`), or the paper's linear
        least-squares start. Default "auto" for log-chord, "linear" for the paper's forms. An
        array is a certified spherical triangulation of the mesh to start from (unit vectors,
        ``connectivity``'s numbering), for instance a coarser mesh's solution carried over
        (:mod:`sphere_nlp.hierarchy`).
    settings : SolverSettings, optional
        The tuning constants (default :class:`~sphere_nlp.settings.SolverSettings` ()), and the
        ``on_run`` hook.
    corner_floor, area_floor : float, optional
        Override ``settings.corner_floor`` (in the area modes ``settings.area_mode_corner_floor``)
        and ``settings.area_floor``: log-chord bounds u >= corner_floor x beta per corner (more
        for a corner whose target is small, :func:`floor_bounds`) and e >= area_floor x 4 pi / t
        per triangle; 0 disables a floor. A triangle of the start below the floor is lifted to it
        when ``area_floor`` is given (the floor then holds at the end), else only if it is within
        ``settings.max_floor_lift`` of it (by default none: it keeps its own size as bound, less
        ``settings.below_floor_slack`` in log e).
    excess_band : ((t,) array, (t,) array), optional
        Log-chord: lower and upper bounds on every triangle's log excess, kept by the margin stage
        and the projection (the polish of an authalic map keeps each triangle's area ratio from
        moving away from its target: :func:`sphere_nlp.polish.no_worse_band`).

    Returns
    -------
    AngleSolution
    """
    settings = DEFAULT_SETTINGS if settings is None else settings
    if not isinstance(settings, SolverSettings):
        raise UsageError("settings must be a sphere_nlp.SolverSettings, not %s" % type(settings).__name__)
    check_floors(corner_floor, area_floor)
    if corner_floor is not None:
        settings = settings.replace(**{"area_mode_corner_floor" if targets.area_weight > 0 else "corner_floor":
                                       float(corner_floor)})
        if corner_floor == 0:                    # no corner floors at all: the margin alone
            settings = settings.replace(small_corner_floor=0.0, area_mode_small_corner_floor=0.0, sliver_band=0.0)
    if area_floor is not None:
        # A floor asked for holds at the end: every triangle of the start below it is lifted to it.
        settings = settings.replace(area_floor=float(area_floor), max_floor_lift=np.inf)
    if on_limit not in ON_LIMIT:
        raise ValueError("on_limit must be one of %s, not %r" % (ON_LIMIT, on_limit))
    if start is None:
        start = "auto" if formulation == "log-chord" else "linear"
    gauge = settings.start_gauge if targets.area_weight == 0 else "area"
    # Large arrays stay on the heap for the whole solve (sphere_nlp.heap).
    with arrays_on_heap():
        began = time.perf_counter()
        initial = initial_point(connectivity, targets, start, vertices, gauge, progress)
        start_s = time.perf_counter() - began
        if initial.kind == "embedding-invalid":
            # Its angles and excesses are those of folded triangles, some negative: no log-chord
            # start, and nothing IPOPT could be trusted to recover from.
            solution = without_valid_start(connectivity, targets, initial.positions, initial.kind)
            solution.start_s = start_s
            return solution
        if (formulation == "log-chord" and targets.mode in AREA_MODE_OF
                and targets.area_weight == 0 and isinstance(start, str)
                and excess_band is None and unplaceable_start(initial, targets, settings)):
            solution = without_valid_start(connectivity, targets, initial.positions, initial.kind,
                                           UNPLACEABLE_START)
            solution.start_positions, solution.start_s = initial.positions, time.perf_counter() - began
            return solution
        context = _Context.make(connectivity, targets, formulation, settings, ipopt_options, max_iter, max_time,
                                progress, initial)
        context.log_e_band = excess_band
        solution = (_solve_with_corner_floor(context, on_limit) if formulation == "log-chord"
                    else _solve_paper_form(context))
    solution.start_s = start_s
    return solution


NO_VALID_START = "No_Valid_Start"
# The angle modes' start shows limbs shrunk past what double precision holds (unplaceable_start).
UNPLACEABLE_START = "Unplaceable_Start"


def unplaceable_start(initial, targets, settings=DEFAULT_SETTINGS):
    """Whether an angle mode's start is floor-crowded (at least ``settings.floor_crowd_share`` of
    its triangles below the area floor) with at least ``settings.unplaceable_corner_share`` of its
    corners below their floors (:func:`floor_bounds`).

    The conformal map shrinks a thin limb like e^-s along s radii: a tail of 60 radii would need
    triangles near e^-120 of their share, which double precision cannot place, so the start's tips
    are degenerate and the angle optimum under the floors is a strongly non-conformal tail with
    thousands of bounds binding, which IPOPT crawls towards (docs/tuning.md,
    "unplaceable_corner_share"). Of the bodies whose limbs are placeable, none left more than 0.9%
    of its corners below their floors; the tailed ones, 2-3%.
    """
    if settings.unplaceable_corner_share <= 0:
        return False
    log_u_floor, log_e_floor = floor_bounds(targets, settings)
    if not floor_crowded(initial.excess, log_e_floor, settings):
        return False
    below = np.mean(~(_log_u(initial.angles, initial.excess) >= log_u_floor))
    return bool(below >= settings.unplaceable_corner_share)


def floor_crowded(excess, log_e_floor, settings=DEFAULT_SETTINGS):
    """Whether at least ``settings.floor_crowd_share`` of the triangles (excesses ``excess``) lie
    below the area floor (``log_e_floor``, :func:`floor_bounds`): a start with thin limbs."""
    with np.errstate(divide="ignore"):
        return bool(np.mean(np.log(excess) < log_e_floor) >= settings.floor_crowd_share)


def without_valid_start(connectivity, targets, positions, start, status=NO_VALID_START):
    """The failed solution (``status``, by default :data:`NO_VALID_START`; no iterations) of a start
    that is not a valid map: no conformal map could be untangled and the convex embedding rounds to
    folded triangles (parts too thin for double precision). Its angles are the folded map's. With
    :data:`UNPLACEABLE_START`: of a valid start the angle modes do not solve from
    (:func:`unplaceable_start`)."""
    with np.errstate(all="ignore"):
        angles, excess = angles_and_excess(positions, connectivity.faces)
        objective = objective_value(targets, angles, excess)
        violation = max_constraint_violation(connectivity, angles, excess)
    return AngleSolution(angles=angles, excess=excess, success=False, status=status, iterations=0,
                         objective=objective, max_constraint_violation=violation, stages=[],
                         initial_angles=angles, initial_excess=excess, start=start, converged=False)


def stage_iteration_cap(n_vertices, settings=DEFAULT_SETTINGS):
    """The iteration cap of every IPOPT run of a log-chord solve without the caller's ``max_iter``:
    max(``settings.min_stage_iterations``, ``settings.stage_iterations_per_vertex`` x n).

    The shared meshes' stages take 4-50 iterations in the angle modes (a few hundred in the area
    modes from the conformal start); a spike 60 radii long on a 162-vertex sphere crawled for 3,000
    in the margin stage, within 0.01% of its optimum after 150 (docs/tuning.md).

    >>> stage_iteration_cap(162), stage_iteration_cap(15000), stage_iteration_cap(43243)
    (300, 1500, 4324)
    """
    return int(max(settings.min_stage_iterations, round(settings.stage_iterations_per_vertex * n_vertices)))


def check_floors(corner_floor, area_floor):
    """UsageError unless each floor is None or a number in [0, 1)."""
    for name, value in (("corner_floor", corner_floor), ("area_floor", area_floor)):
        if value is not None and not (isinstance(value, (int, float, np.floating)) and 0 <= value < 1):
            raise UsageError("%s must be a number in [0, 1) (0 disables it), not %r" % (name, value))


def floor_bounds(targets, settings):
    """The floors as lower bounds: log u per corner (3t,) and log e per triangle (t,).

    log u >= log max(margin, f x beta), f the mode's corner floor, or its small-corner floor
    (``small_corner_floor``, ``area_mode_small_corner_floor``) if larger for a corner whose target
    beta is below ``small_corner_angle`` (and in the area modes at least
    ``area_mode_sliver_angle``); log e >= log(area floor x 4 pi / t) (-inf if 0).

    Examples
    --------
    >>> from sphere_nlp.targets import Targets
    >>> angles = np.radians([[60.0, 60.0, 60.0], [5.0, 5.0, 170.0]])
    >>> tg = Targets(angles, np.full(2, 2 * np.pi), 1.0, 0.0, "custom")
    >>> u, e = floor_bounds(tg, DEFAULT_SETTINGS)
    >>> (np.exp(u) / angles.ravel()).round(4).tolist(), round(float(np.exp(e[0]) / (2 * np.pi)), 20)
    ([0.1, 0.1, 0.1, 0.5, 0.5, 0.1], 1e-12)
    >>> sliver = np.radians([[0.5, 5.0, 174.5]])
    >>> area = Targets(np.r_[angles, sliver], np.full(3, 2 * np.pi), 0.01, 1.0, "custom")
    >>> u, _ = floor_bounds(area, DEFAULT_SETTINGS.replace(area_mode_small_corner_floor=0.5))
    >>> (np.exp(u) / area.angles.ravel()).round(6).tolist()[3:]   # 170, 0.5 and 174.5 degrees: the margin
    [0.5, 0.5, 3.4e-05, 0.011459, 0.5, 3.3e-05]
    """
    area = targets.area_weight > 0
    fraction = settings.area_mode_corner_floor if area else settings.corner_floor
    small = settings.area_mode_small_corner_floor if area else settings.small_corner_floor
    beta = np.asarray(targets.angles, float).ravel()
    small_target = beta < settings.small_corner_angle
    if area:
        small_target &= beta >= settings.area_mode_sliver_angle
    fraction = np.where(small_target, max(fraction, small), fraction)
    log_u = np.log(np.maximum(settings.angle_margin, fraction * beta))
    t = len(targets.excess)
    with np.errstate(divide="ignore"):
        log_e = np.full(t, np.log(settings.area_floor * 4 * np.pi / t))
    return log_u, log_e


def sliver_band_bounds(targets, settings):
    """Bounds on log u (3t,) that keep the shape of the target's slivers, or None if there are none.

    Angle modes: in a triangle whose target has a corner below 1 degree, the two smallest corners
    a, b keep u within a relative ``settings.sliver_band`` x (a + b) of their targets, where
    that is at most 0.5 (a sliver with one small corner, a needle, has no such pair and no band).
    Its apex moves along its base by (change of b - change of a) / (a + b) of its height,
    so without the band a few per cent of error in 0.1-degree corners shears it 30-fold
    (koala.obj: worst quasi-conformal ratio 1,556 against its 3D shape; docs/tuning.md).

    Returns
    -------
    (lower, upper) : pair of (3t,) arrays (-inf and inf off the band), or None

    Examples
    --------
    >>> from sphere_nlp.targets import Targets
    >>> angles = np.radians([[60.0, 60.0, 60.0], [0.2, 179.5, 0.3], [0.5, 89.75, 89.75]])
    >>> tg = Targets(angles, np.full(3, 4 * np.pi / 3), 1.0, 0.0, "custom")
    >>> lower, upper = sliver_band_bounds(tg, DEFAULT_SETTINGS)
    >>> np.isfinite(upper).nonzero()[0].tolist()       # the cap's two small corners only
    [3, 5]
    >>> (np.exp(upper[[3, 5]]) / angles[1, [0, 2]] - 1).round(4).tolist()   # 2.5 x 0.5 degrees
    [0.0218, 0.0218]
    """
    if targets.area_weight > 0 or settings.sliver_band <= 0:
        return None
    beta = np.asarray(targets.angles, float)
    order = np.argsort(beta, axis=1)[:, :2]
    small = np.take_along_axis(beta, order, axis=1)
    width = settings.sliver_band * small.sum(axis=1)
    banded = ((small[:, 0] < np.radians(1.0)) & (width <= 0.5)
              & (small[:, 0] * (1 - width) > settings.angle_margin))
    if not banded.any():
        return None
    corners = (3 * np.flatnonzero(banded)[:, None] + order[banded]).ravel()
    target = beta.ravel()[corners]
    half = np.repeat(width[banded], 2)
    lower, upper = np.full(beta.size, -np.inf), np.full(beta.size, np.inf)
    lower[corners], upper[corners] = np.log(target * (1 - half)), np.log(target * (1 + half))
    return lower, upper


@dataclass
class _Context:
    """What the stages of one solve share: the problem, the IPOPT options, the log of runs.

    ``options`` are every run's IPOPT options, ``warm_options`` those of a run warm-started from
    another's multipliers, ``first_options`` those of the first margin run (a small initial barrier
    in the angle modes and after a skipped walk; None: ``options``); ``walk`` whether the area
    modes walk first; ``window`` is the half-width of the trust region on the log excesses;
    ``stages`` collects the record of every run.
    """

    connectivity: object
    targets: object
    formulation: str
    settings: object
    options: dict
    warm_options: dict
    first_options: dict
    progress: object
    initial: object
    dropped: list
    hessian: str
    window: float
    log_u_floor: np.ndarray = None
    log_e_floor: np.ndarray = None
    log_e_lower: np.ndarray = None
    log_u_band: tuple = None
    log_e_band: tuple = None
    walk: bool = False
    stage_cap: int = None
    solve_targets: object = None
    stages: list = field(default_factory=list)

    @classmethod
    def make(cls, connectivity, targets, formulation, settings, ipopt_options, max_iter, max_time, progress,
             initial):
        area_mode = targets.area_weight > 0
        options = dict(settings.ipopt_options)
        if area_mode and formulation == "log-chord":
            options.update(settings.area_mode_ipopt_options)
        if max_iter is not None:
            options["max_iter"] = int(max_iter)
        if max_time is not None:
            options["max_wall_time"] = float(max_time)
        if connectivity.n_vertices >= settings.multiplier_estimate_max_vertices:
            options["constr_mult_init_max"] = 0.0
        options.update(ipopt_options or {})
        stage_cap = None
        if formulation == "log-chord" and max_iter is None and "max_iter" not in (ipopt_options or {}):
            # No iteration limit asked for: the size's cap, whose stop is projected (not a failure).
            cap = stage_iteration_cap(connectivity.n_vertices, settings)
            if cap < int(options.get("max_iter", 3000)):
                options["max_iter"] = stage_cap = cap
        # Warm-started runs: small barrier and bound pushes, but the caller's options still win.
        warm_options = dict(options, **settings.warm_start_options)
        warm_options.update(ipopt_options or {})
        first_options = None
        log_u_floor, log_e_floor = floor_bounds(targets, settings)
        walk = area_mode and start_area_distance(initial.excess, targets.excess) > settings.area_walk_distance
        if not walk:
            # A start near the optimum: a small first barrier keeps the solve near it; but where
            # much of the start lies below the area floor (thin limbs), those triangles' bounds bind
            # one after another under it, and a larger first barrier takes fewer steps.
            first_options = dict(options, **(settings.near_start_options if area_mode else
                                             settings.floor_crowd_margin_options
                                             if floor_crowded(initial.excess, log_e_floor, settings)
                                             else settings.angle_mode_margin_options))
            first_options.update(ipopt_options or {})
        # The three redundant vertex sums (7) left out, at vertices of the valid start (none for
        # the linear guess, whose positions are unknown).
        dropped = (independent_vertices(initial.positions, connectivity.vertex_degree)
                   if initial.positions is not None else [])
        return cls(connectivity=connectivity, targets=targets, formulation=formulation, settings=settings,
                   log_u_floor=log_u_floor, log_e_floor=log_e_floor,
                   log_u_band=sliver_band_bounds(targets, settings),
                   options=options, warm_options=warm_options, first_options=first_options, progress=progress,
                   initial=initial, dropped=dropped, walk=walk, stage_cap=stage_cap,
                   solve_targets=summed_targets(connectivity, targets, np.flatnonzero(
                       dropped_sum_drift(connectivity, targets, settings.dropped_penalty) > settings.max_sum_drift)),
                   hessian=settings.area_mode_hessian if area_mode else settings.angle_mode_hessian,
                   window=settings.excess_window if area_mode else settings.angle_mode_excess_window)

    @property
    def n_faces(self):
        return self.connectivity.n_faces

    def nlp(self, obtuse_corners, targets=None, dropped_vertices=None, **keywords):
        """The log-chord NLP with this solve's left-out vertices, Hessian, margin and penalty."""
        keywords.setdefault("dropped_penalty", self.settings.dropped_penalty)
        keywords.setdefault("log_u_band", self.log_u_band)
        keywords.setdefault("semidefinite_below_excess",
                            self.settings.semidefinite_block_share * 4 * np.pi / self.n_faces)
        return LogChordNLP(self.connectivity, self.solve_targets if targets is None else targets,
                           dropped_vertices=self.dropped if dropped_vertices is None else dropped_vertices,
                           obtuse_corners=obtuse_corners, hessian=self.hessian,
                           angle_margin=self.settings.angle_margin, **keywords)

    def obtuse_at(self, nlp, x):
        """The corners to write in the obtuse form of (8) for a stage starting at x (AngleNLP)."""
        return nlp.unpack(x)[0] > self.settings.obtuse_angle

    def capped(self, run):
        """Whether the size's iteration cap (``stage_cap``), not the caller's limits, stopped ``run``."""
        return self.stage_cap is not None and run.status == "Maximum_Iterations_Exceeded"

    def stage_progress(self, name):
        """The caller's progress function for the stage ``name``, or None."""
        if self.progress is None:
            return None
        return lambda it, f, viol, elapsed: self.progress(name, it, f, viol, elapsed)

    def diverged(self, nlp, run):
        # A run the divergence watch stopped has left the solution set by IPOPT's own measure of
        # (8) in log chords, even where the cosine form of (8) is still small at its end
        # (nefertiti.obj equal-areas: IPOPT's violation 24 after the margin stage ran off).
        return status_kind(run.status) == "diverged" or diverged(self.connectivity, nlp, run.x, self.settings)

    def violation(self, nlp, run):
        return max_constraint_violation(self.connectivity, *nlp.unpack(run.x))

    def excess_bounds(self, lower, upper):
        return within_band(lower, upper, self.log_e_band)


def within_band(lower, upper, band):
    """Bounds on log e: (lower, upper) narrowed to ``band`` (lower, upper) where one is given."""
    if band is None:
        return lower, upper
    return np.maximum(lower, band[0]), np.minimum(upper, band[1])


def run_ipopt(nlp, name, x, settings, stages=None, **solve_keywords):
    """One IPOPT run of ``nlp`` from x (:meth:`AngleNLP.solve` with ``solve_keywords``), named
    ``name``: shown to ``settings.on_run`` (and ``on_iterate``, ``modify_hessian``) and recorded
    in ``stages`` (if given).

    ``on_run(name, nlp, run)`` may return an :class:`~sphere_nlp.nlp.IpoptRun` to use instead (for
    experiments and tests, e.g. to inject a failure); None keeps the run.
    """
    if settings.on_iterate is not None:
        solve_keywords["on_iterate"] = lambda *iterate: settings.on_iterate(name, *iterate)
    if settings.modify_hessian is not None:
        solve_keywords["modify_hessian"] = lambda *arguments: settings.modify_hessian(name, *arguments)
    run = nlp.solve(x, **solve_keywords)
    if settings.on_run is not None:
        replaced = settings.on_run(name, nlp, run)
        run = run if replaced is None else replaced
    if stages is not None:
        stages.append(_stage_record(name, run))
    return run


def _solve_with_corner_floor(context, on_limit):
    """The log-chord solve, with the corner floors as bounds from the start (``corner_floor_pass``
    "start", the default) or only where the optimum needs them ("needed").

    "needed": the solve runs first with every corner bounded by the margin alone; only if its
    result has a corner below its floor (``corner_floor`` x beta) is the mesh solved again from
    the start with the floors as bounds, in stages named "corner-floor-<stage>". The floors rarely
    bind at the optimum, but as bounds from the start they can obstruct the path to it, while on
    other meshes they keep the path from collapsing corners (both measured in equal-angles from the
    surface's conformal map, which that mode no longer starts from; docs/tuning.md).
    """
    floors, margin = context.log_u_floor, np.log(context.settings.angle_margin)
    if context.settings.corner_floor_pass == "start" or not np.any(floors > margin):
        return _solve_log_chord(context, on_limit)
    context.log_u_floor = np.full_like(floors, margin)
    first = _solve_log_chord(context, on_limit)
    context.log_u_floor = floors
    below = np.any(~(_log_u(first.angles, first.excess) >= floors - 1e-9))
    # A first pass stopped by the caller's limits is the answer (a second would hit them again).
    if (first.success and not below) or status_kind(first.status) == "limit" or interrupts.deadline_passed():
        first.floor_corners = _floor_counts(context, first.angles, first.excess)[0]
        return first
    done = len(context.stages)
    second = _solve_log_chord(context, on_limit)      # its iterations count both passes' stages
    for stage in context.stages[done:]:
        stage["name"] = "corner-floor-" + stage["name"]
    return second


def _log_u(angles, excess):
    """log u = log(alpha - e/2) of every corner, (3t,) (nan or -inf where u <= 0)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.log((angles - excess[:, None] / 2).ravel())


def _solve_log_chord(context, on_limit):
    """The log-chord stages (the module docstring), top down."""
    settings, initial = context.settings, context.initial
    # Corners obtuse at the start get the well-conditioned form of (8) near pi (AngleNLP).
    obtuse = initial.angles > settings.obtuse_angle
    nlp = context.nlp(obtuse)
    x0 = x_start = nlp.pack(initial.angles, initial.excess)
    if context.walk:
        # Each step, and the stages after the walk, flag the corners obtuse at their own start:
        # the areas reshape the triangles.
        weights = continuation_area_weights(context.targets, settings.area_continuation_weighting)
        x_start = area_continuation(lambda tg, x: context.nlp(context.obtuse_at(nlp, x), tg, area_form="log",
                                                              log_area_weights=weights),
                                    context.solve_targets, x0, context.n_faces, context.options,
                                    progress=context.stage_progress("area-continuation"), stages=context.stages,
                                    settings=settings, log_floor=context.log_u_floor)
        obtuse = context.obtuse_at(nlp, x_start)
        nlp = context.nlp(obtuse)
    run, log_u_lower = margin_stage(context, nlp, x_start)
    run = resume_diverged(context, nlp, run, log_u_lower)
    if (on_limit == "project" or context.capped(run)) and run.stopped_by_limit and run.finite:
        # Stopped by the caller's limits, or by the size's cap (stage_iteration_cap): hand back
        # its iterate made feasible, if that works.
        projected = _projected_solution(context, nlp, run, log_u_lower)
        if projected.success:
            return projected
    if interrupts.deadline_passed():
        # The run's time is up (interrupts.deadline): no fallback stage, each would be built only
        # to stop at once (bipyramid(1000): 6.7 s of building after the limit).
        return _solution(context, *nlp.unpack(run.x), run)
    with_margin = True
    if context.diverged(nlp, run):
        # The direct margin stage ran away from the solution set (hand_closed.obj original-areas:
        # violation 5.5): the equality stage first.
        run, with_margin, log_u_lower = equality_fallback(context, nlp, x_start, x0)
    nlp, run, violation = restore_dropped_sums(context, nlp, run, obtuse, with_margin, log_u_lower)
    if violation > settings.feasibility_tolerance:
        nlp, run = all_constraints_stage(context, obtuse, x_start)
    return _solution(context, *nlp.unpack(run.x), run)


def windowed_solve(context, nlp, x_start, name, inequalities=False, recentre=True, log_u_lower=None,
                   warm_from=None, first_options=None, log_e_lower=None):
    """IPOPT runs of one stage inside a window on the log excesses, re-centred while they end on it.

    Bounds log e within ``context.window`` of the current point act as a trust region: when most
    triangles are tiny, scaling all their excesses together barely changes (6)-(8) and, in the
    angle modes, not the objective either, so IPOPT took huge steps along that flat direction
    (armadillo.obj, 43k vertices: diverged; with the window 17 iterations). The barrier terms also
    convexify it. If the result touches the window, re-centre and repeat with a window
    ``settings.window_growth`` times wider, warm-started (if ``recentre``, at most
    ``settings.max_window_rounds`` runs), else report it as touched (``run.touched``).

    Parameters
    ----------
    context : _Context
    nlp : AngleNLP
    x_start : array
    name : str
        The stage's name; re-centred runs are named ``name + "-recentred"``.
    inequalities : bool
        Keep log u >= ``log_u_lower`` (AngleNLP.solve).
    log_u_lower : (3t,) array, optional
        Lower bounds on log u per corner (default: the margin everywhere).
    log_e_lower : (t,) array, optional
        Lower bounds on log e per triangle, kept inside every window (default: the window's own).
    warm_from : IpoptRun or Iterate, optional
        An earlier run (or one of its iterates) with the same equality constraints whose
        multipliers (``lam_g``, ``lam_x``) start this one.
    first_options : dict, optional
        IPOPT options of a run that is not warm-started (default ``context.options``).

    Returns
    -------
    IpoptRun
        The last run, with ``touched`` set.
    """
    settings, t = context.settings, context.n_faces
    x, window, previous = x_start, context.window, warm_from
    for round_ in range(settings.max_window_rounds):
        log_e = x[3 * t:]
        run_options, warm = first_options or context.options, {}
        if previous is not None:
            run_options = context.warm_options
            lam_x = previous.lam_x.copy()
            lam_x[3 * t:] = 0.0               # the old window's bounds are gone
            warm = dict(lam_g0=previous.lam_g, lam_x0=lam_x)
        lower = log_e - window if log_e_lower is None else np.maximum(log_e - window, log_e_lower)
        run = run_ipopt(nlp, name if round_ == 0 else "%s-recentred" % name, x, settings, context.stages,
                        inequalities=inequalities, options=run_options, progress=context.stage_progress(name),
                        excess_bounds=context.excess_bounds(lower, log_e + window), log_u_lower=log_u_lower,
                        abort_violation=settings.abort_violation, abort_iterations=settings.abort_iterations,
                        sound_violation=settings.sound_violation, **warm)
        moved = np.max(np.abs(run.x[3 * t:] - log_e), initial=0.0)
        run.touched = bool(moved >= 0.99 * window)
        if not run.success or not run.finite or not run.touched or not recentre:
            return run
        x, previous = run.x, run
        window *= settings.window_growth
    return run


def margin_stage(context, nlp, x_start):
    """The first stage after the start (and the continuation): (9) with u >= the margin.

    Straight to the margin stage: the optimum is often at a degenerate triangle (area modes nearly
    always), which an equality stage chases towards log u = -inf before the margin stage starts
    again anyway (docs/tuning.md, "angle_mode_excess_window"). Corners already below the margin at
    ``x_start`` keep their own size less 10% as bound (:func:`margin_restart`). The floors
    (:func:`floor_bounds`) are the margin of each corner and a lower bound on each log e; a corner
    of the start below its floor by more than ``max_margin_lift`` in the log keeps its own size less
    10% as bound; a triangle below the area floor by at most ``max_floor_lift`` in the log is
    lifted to it, one further below keeps its own size, less ``below_floor_slack``
    (:func:`area_floor_restart`).

    Returns
    -------
    run : IpoptRun
    log_u_lower : (3t,) array
        The stage's lower bounds on log u.
    """
    restart, log_u_lower, _ = margin_restart(x_start, x_start, context.n_faces, nlp.angle_margin,
                                             context.settings.max_margin_lift, log_floor=context.log_u_floor)
    restart, context.log_e_lower = area_floor_restart(restart, context.n_faces, context.log_e_floor,
                                                      context.settings.max_floor_lift,
                                                      context.settings.below_floor_slack)
    run = windowed_solve(context, nlp, restart, "margin", inequalities=True, log_u_lower=log_u_lower,
                         first_options=context.first_options, log_e_lower=context.log_e_lower)
    return run, log_u_lower


def resume_diverged(context, nlp, run, log_u_lower):
    """After a margin stage that left the solution set: the margin stage again, warm-started from
    the best iterate it had near the constraints (``run.best_sound``), at most
    ``settings.diverged_resumes`` times.

    A long stage can make most of its way to an optimum and then run off in a few steps (the
    filter then accepts a growing violation); its progress up to there is worth keeping, where the
    equality fallback would start again from the stage's start. Returns ``run`` itself if it did not
    diverge, had no such iterate beyond its start, or the run's time is up.
    """
    for _ in range(context.settings.diverged_resumes):
        best = run.best_sound
        if (not context.diverged(nlp, run) or best is None or best.iteration == 0
                or interrupts.deadline_passed()):
            return run
        run = windowed_solve(context, nlp, best.x, "margin-resumed", inequalities=True,
                             log_u_lower=log_u_lower, warm_from=best, log_e_lower=context.log_e_lower)
    return run


def equality_fallback(context, nlp, x_start, x0):
    """After a diverged margin stage: the equalities alone from ``x_start``, then the margin again.

    The equality run gets one window: a run that ends on it is continued by the margin stage
    instead of being re-centred, because the triangles that pull it are often degenerating slivers
    (docs/tuning.md, "max_window_rounds"). If it degenerates, touches the window or diverges, the
    margin stage runs again, from the equality result if usable (not diverged; its corners can look
    fine even then), warm-started with its multipliers, else from the feasible start ``x0`` (in the
    angle modes ``x_start`` is ``x0``; the continuation's end is known to fail). The equality
    result is used however far its corners are below the margin: they keep their own size, less
    10%, as bound (:func:`margin_restart`).

    Returns
    -------
    run : IpoptRun
    with_margin : bool
        Whether ``run`` kept the margin (its stage had the inequalities).
    log_u_lower : (3t,) array or None
        Its lower bounds on log u.
    """
    run = windowed_solve(context, nlp, x_start, "equality", recentre=False)
    equality_diverged = context.diverged(nlp, run)
    # Its corners and triangles must clear their floors (the margin and the corner floors, the
    # area floor), else the margin stage follows from it.
    t3 = 3 * context.n_faces
    if (run.success and not run.touched and not equality_diverged
            and np.all(run.x[:t3] > context.log_u_floor) and np.all(run.x[t3:] >= context.log_e_floor)):
        return run, False, None
    x_equality = x0 if equality_diverged else run.x
    restart, log_u_lower, from_equality = margin_restart(x_equality, x0, context.n_faces, nlp.angle_margin,
                                                         context.settings.max_margin_lift, any_lift=True,
                                                         log_floor=context.log_u_floor)
    restart, context.log_e_lower = area_floor_restart(restart, context.n_faces, context.log_e_floor,
                                                      context.settings.max_floor_lift,
                                                      context.settings.below_floor_slack)
    run = windowed_solve(context, nlp, restart, "margin", inequalities=True, log_u_lower=log_u_lower,
                         warm_from=run if from_equality else None, log_e_lower=context.log_e_lower)
    return run, True, log_u_lower


def restore_dropped_sums(context, nlp, run, obtuse, with_margin, log_u_lower):
    """If the three left-out vertex sums have not come back, raise their penalty 100-fold at a
    time (up to ``settings.max_dropped_penalty``) and solve again from there.

    They come back by themselves only near the solution set (the redundancy is infinitesimal);
    with a weak penalty the solver can stop at a metric whose sums are off (docs/tuning.md,
    "max_dropped_penalty").

    Returns
    -------
    nlp : AngleNLP
        The NLP of the last run.
    run : IpoptRun
    violation : float
        Its max constraint violation.
    """
    settings = context.settings
    penalty = settings.dropped_penalty
    violation = context.violation(nlp, run)
    while violation > settings.feasibility_tolerance and run.finite and penalty < settings.max_dropped_penalty:
        penalty *= 100
        nlp = context.nlp(obtuse, dropped_penalty=penalty)
        run = windowed_solve(context, nlp, run.x, "penalty-%.0e" % penalty, inequalities=with_margin,
                             log_u_lower=log_u_lower, log_e_lower=context.log_e_lower if with_margin else None)
        violation = context.violation(nlp, run)
    return nlp, run, violation


def all_constraints_stage(context, obtuse, x_start):
    """The last resort: every vertex sum (7) kept, from ``x_start`` (a singular Jacobian at the
    solution, so slow). Returns (nlp, run)."""
    nlp = context.nlp(obtuse, dropped_vertices=())
    return nlp, windowed_solve(context, nlp, x_start, "all-constraints")


def _projected_solution(context, nlp, stopped, log_u_lower):
    """The AngleSolution of a stage stopped by the caller's limits (or the size's iteration cap: its
    record gets ``iteration_cap``), projected onto the constraints."""
    if context.capped(stopped) and context.stages:
        context.stages[-1]["iteration_cap"] = context.stage_cap
    # Past the run's deadline (interrupts.deadline) the projection gets a short grace of its own.
    grace = PROJECTION_GRACE_FRACTION * float(context.options.get("max_wall_time", 0.0)) + PROJECTION_GRACE_S
    with interrupts.extended_deadline(grace):
        projection = project_onto_constraints(context.connectivity, context.targets, nlp, stopped.x,
                                              context.formulation, context.dropped, context.options,
                                              log_u_lower, context.window,
                                              progress=context.stage_progress("projection"),
                                              settings=context.settings, stages=context.stages,
                                              excess_band=context.log_e_band)
    return _solution(context, *nlp.unpack(projection.x), projection, stopped_status=stopped.status)


def _solve_paper_form(context):
    """The faithful and substituted forms, staged as in section 4 of the paper (module docstring)."""
    settings, initial = context.settings, context.initial
    nlp = AngleNLP(context.connectivity, context.targets, context.formulation)
    x_initial = nlp.pack(initial.angles, initial.excess)
    run = run_ipopt(nlp, "equality", x_initial, settings, context.stages, inequalities=False,
                    options=context.options, progress=context.stage_progress("equality"))
    if violates_inequalities(*nlp.unpack(run.x)):
        run = run_ipopt(nlp, "inequality", run.x, settings, inequalities=True, lam_g0=run.lam_g,
                        options=context.warm_options, progress=context.stage_progress("inequality"))
        if not run.success:
            # A warm start from an infeasible point can stall; a cold start with the default barrier
            # parameter is slower but robust.
            run = run_ipopt(nlp, "inequality-cold", x_initial, settings, inequalities=True,
                            options=dict(context.options), progress=context.stage_progress("inequality-cold"))
        context.stages.append(_stage_record("inequality", run))
    return _solution(context, *nlp.unpack(run.x), run)


def diverged(connectivity, nlp, x, settings=DEFAULT_SETTINGS):
    """Whether a run ended far from the solution set (not merely short of the tolerance):
    non-finite, or a max violation above ``settings.diverged_violation``."""
    if not np.isfinite(x).all():
        return True
    return max_constraint_violation(connectivity, *nlp.unpack(x)) > settings.diverged_violation


def margin_restart(x_equality, x_start, n_faces, angle_margin, max_lift=DEFAULT_SETTINGS.max_margin_lift,
                   any_lift=False, log_floor=None):
    """Where the margin stage starts, and its lower bounds on log u per corner.

    From the equality stage's result if it is finite and lifting its corners to the margin changes
    none by more than a factor exp(max_lift) (corners already below the margin at the start: none
    below their start size by more), else from the stage's own start: a corner the equality stage drove
    far below the margin (armadillo_remeshed.obj equal-areas: u = 1e-8), lifted to it, broke (8) by
    ~7, the margin stage failed and the last-resort solve ran for over an hour. Corners of that
    start which are themselves below the margin (nefertiti.obj's start in the excess gauge has a
    180-degree triangle with corners of 6e-7 rad) keep their own size, less 10%, as their bound;
    so do the equality result's corners more than ``max_lift`` below the margin; with ``any_lift``
    the (finite) equality result is used however far its corners are below (once the stage's start
    is known to fail).

    Returns
    -------
    restart : array
        A copy, with corners just inside their bounds.
    log_u_lower : (3 n_faces,) array
    from_equality : bool
        Whether ``restart`` is the equality result (else the stage's start).

    ``log_floor`` (3 n_faces,), if given, is each corner's margin in log u instead of
    log(angle_margin) (the corner floors, :func:`floor_bounds`). A corner between the angle margin
    less ``max_lift`` and its floor is lifted to the floor, however far that is: the floors are
    what the caller asked the map to keep (an area mode's walk ends with corners near the margin
    that a floor of 0.1 beta is a hundred times above); only a corner far below the angle margin
    itself keeps its own size.
    """
    angle_floor = np.log(angle_margin)
    margin = angle_floor if log_floor is None else np.asarray(log_floor, float)
    restart = x_start
    # A corner already below the margin at the start counts from its own size there: nefertiti.obj
    # has two of 6e-7 rad, which grew to 7e-6 in the equality stage; measured from the margin they
    # sent the margin stage back to the start (14 iterations to regain the equality objective).
    floor = np.minimum(margin, x_start[:3 * n_faces])
    from_equality = bool(np.isfinite(x_equality).all()
                         and (any_lift or np.all(x_equality[:3 * n_faces] > floor - max_lift)))
    restart = np.array(x_equality if from_equality else x_start, float)
    log_u = restart[:3 * n_faces]
    log_u_lower = np.where(log_u < np.minimum(margin, angle_floor) - max_lift, log_u - 0.1, margin)
    restart[:3 * n_faces] = np.maximum(log_u, log_u_lower + 1e-3)
    return restart, log_u_lower, from_equality


def area_floor_restart(x, n_faces, log_e_floor, max_lift=DEFAULT_SETTINGS.max_margin_lift,
                       slack=DEFAULT_SETTINGS.below_floor_slack):
    """The area floor's bounds on log e for a stage starting at x, and x just inside them.

    As for the corners (:func:`margin_restart`): a triangle below its floor by less than
    ``max_lift`` in log e is lifted to it, one further below keeps its own size as bound, less
    ``slack`` in log e.

    Returns
    -------
    restart : array (a copy)
    log_e_lower : (n_faces,) array

    Examples
    --------
    >>> x = np.log([1.0, 1.0, 1.0, 1e-3, 1e-12])
    >>> restart, lower = area_floor_restart(x, 1, np.full(1, np.log(1e-10)))
    >>> bool(lower[0] == np.log(1e-10)), bool(restart[3] > lower[0])
    (True, True)
    """
    restart = np.array(x, float)
    log_e = restart[3 * n_faces:]
    log_e_lower = np.where(log_e < log_e_floor - max_lift, log_e - slack, log_e_floor)
    restart[3 * n_faces:] = np.maximum(log_e, log_e_lower + 1e-3)
    return restart, log_e_lower


def area_continuation(nlp_for, targets, x0, n_faces, options, progress=None, stages=None,
                      settings=DEFAULT_SETTINGS, log_floor=None):
    """Walk the log excesses from the start's to the targets' (the area modes' first phase).

    The start (a conformal map) can be far from the area targets: on knight.off some log excesses
    must change by 25. With the objective (9) the pull on a tiny triangle's log excess vanishes
    with its size (d/ds (e^s - e')^2 = 2 e (e - e')) and is non-convex in s, so IPOPT crawled
    (bunny.off original-areas: no result in 120 s) or diverged. This phase instead minimises the
    same weighted sum with the area term (log e - log e'_tau)^2, convex in s with a pull that does
    not fade, for targets e'_tau that move from the start's excesses to e' geometrically in steps
    of at most  ``settings.area_continuation_step`` per log excess, each with at most
    ``settings.area_continuation_iterations`` IPOPT iterations: the point only has to be a good start
    for (9), which the caller then solves from it. A step whose run ends far from the solution set
    (``area_continuation_violation``) is re-run from where it ended, and if that gets no nearer,
    tried again at half the length from the last point reached (``area_continuation_halvings``).
    The steps keep the corners above a floor (:func:`continuation_floor`: the margin, or the
    corner floors ``log_floor`` if given, so that a walk asked to keep corners never collapses
    them); they are named by their fraction of the way ("area-continuation-3/4", "-more1" for a
    re-run).

    Parameters
    ----------
    nlp_for : callable(Targets, x) -> AngleNLP
        Builds the log-area NLP for one set of targets, to be started from the point x.
    targets : Targets
    x0 : array
        Start (log-chord variables) with its own excesses exp(x0[3t:]).
    n_faces : int
    options : dict
        IPOPT options.
    progress : callable(iteration, objective, violation, elapsed), optional
    stages : list, optional
        Stage records are appended here.
    settings : SolverSettings

    Returns
    -------
    x : array
        The last finite point reached (x0 if the first step diverges); it may be slightly
        infeasible when a step was capped.
    """
    start_log = x0[3 * n_faces:]
    target_log = np.log(targets.excess)
    n_steps = max(1, int(np.ceil(np.max(np.abs(target_log - start_log)) / settings.area_continuation_step)))
    # Only a start is needed, so each step is capped (the last iterations of a step refine the
    # weak angle term and are repeated by the next step anyway).
    capped = dict(options, max_iter=min(int(options.get("max_iter", 3000)),
                                        settings.area_continuation_iterations))
    # Exact fractions, so that tau = k / n_steps exactly when no step was halved.
    x, reached, step, halvings = x0, Fraction(0), Fraction(1, n_steps), 0

    def violation(nlp, run):
        if not run.finite:
            return np.inf
        return np.max(np.abs(nlp.evaluate(run.x)[1]))

    while reached < 1:
        tau = min(reached + step, Fraction(1))
        excess = np.exp((1 - float(tau)) * start_log + float(tau) * target_log)
        nlp = nlp_for(replace(targets, excess=excess * (4 * np.pi / excess.sum())), x)
        floor, step_options = {}, capped
        if settings.area_continuation_floor:
            floor = dict(inequalities=True, log_u_lower=continuation_floor(x0, n_faces, nlp.angle_margin,
                                                                           log_floor))
            step_options = dict(capped, **settings.area_continuation_options)
        name = "area-continuation-%s" % tau
        run = run_ipopt(nlp, name, x, settings, stages, options=step_options, progress=progress, **floor)
        ended = violation(nlp, run)
        for attempt in range(1, settings.area_continuation_extra_runs + 1):
            if not settings.area_continuation_violation < ended < np.inf:
                break
            rerun = run_ipopt(nlp, "%s-more%d" % (name, attempt), run.x, settings, stages,
                              options=step_options, progress=progress, **floor)
            rerun_ended = violation(nlp, rerun)
            if rerun_ended >= ended and halvings < settings.area_continuation_halvings:
                break                           # drifting away: halve the step instead
            run, ended = rerun, rerun_ended
        if ended > settings.area_continuation_violation and halvings < settings.area_continuation_halvings:
            # A nearer target, from the last good point: going on from a point far from the
            # solution set only drifted further (see docs/tuning.md).
            halvings, step = halvings + 1, step / 2
            continue
        if ended == np.inf:
            break
        x, reached = run.x, tau
    return x


def start_area_distance(excess, target_excess):
    """How far a start's excesses are from the targets: the mean |log(e / e')| over the triangles.

    The area modes walk only from starts further than ``SolverSettings.area_walk_distance``: the
    conformal start is at 2.1 (bunny.off) to 6.9 (knight.off), area-mode optima at 0.02-0.05
    (docs/tuning.md, "area_walk_distance").

    Examples
    --------
    >>> float(start_area_distance(np.array([1.0, 2.0]), np.array([1.0, 2.0 * np.e])))
    0.5
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.log(np.asarray(excess, float) / np.asarray(target_excess, float))
    return float(np.mean(np.abs(ratio))) if np.isfinite(ratio).all() else np.inf


def continuation_area_weights(targets, weighting="uniform"):
    """Each triangle's weight in the area continuation's term (log e - log e'_tau)^2, (t,).

    "uniform" (``SolverSettings.area_continuation_weighting``'s default): all ones.
    "objective": (e' / e_mean)^2 of the final target e'. Near e = e', (9)'s area term
    ((e - e') / e_mean)^2 equals (e' / e_mean)^2 (log e - log e')^2 to second order, so the walk's
    last step is (9)'s own quadratic model and ends near its optimum, while the pull on a triangle
    far below its target still does not fade with its size. Unweighted ("uniform"), the walk held
    tiny-target triangles to their relative size, which (9) lets go: on bunny.off original-areas
    145 of 6,966 triangles had a corner more than a factor e off its (9)-optimal size (their areas
    up to 18 times) when the last stage began.

    Examples
    --------
    >>> from types import SimpleNamespace
    >>> targets = SimpleNamespace(excess=np.array([1.0, 2.0, 3.0]), excess_scale=2.0)
    >>> continuation_area_weights(targets, "objective")
    array([0.25, 1.  , 2.25])
    """
    if weighting == "uniform":
        return np.ones(len(targets.excess))
    if weighting != "objective":
        raise ValueError("area_continuation_weighting must be 'objective' or 'uniform', not %r" % (weighting,))
    return (np.asarray(targets.excess, float) / targets.excess_scale) ** 2


def continuation_floor(x0, n_faces, angle_margin, log_floor=None):
    """Lower bounds on log u for the area continuation's steps (see ``SolverSettings.area_continuation_floor``).

    ``log(angle_margin)`` for every corner (or its floor ``log_floor``, (3 n_faces,), if given),
    except those already below it at the start ``x0``, which may not shrink below their own start
    size less 10%.

    Examples
    --------
    >>> continuation_floor(np.log([1.0, 1e-6, 0.5, 1.0]), 1, 1e-4).round(2)
    array([ -9.21, -13.92,  -9.21])
    """
    margin = np.log(angle_margin) if log_floor is None else np.asarray(log_floor, float)
    log_u = np.asarray(x0, float)[:3 * n_faces]
    return np.where(log_u < margin, log_u - 0.1, margin)


def project_onto_constraints(connectivity, targets, nlp, x, formulation, dropped, options, log_u_lower,
                             excess_window, progress=None, settings=DEFAULT_SETTINGS, stages=None,
                             excess_band=None):
    """The feasible point nearest a log-chord iterate ``x`` (a stage stopped short), by IPOPT.

    The same constraints and bounds (log u >= ``log_u_lower``, log e within ``excess_window`` of
    ``x``), with the objective (9) replaced by its value's distance from the iterate: targets
    (beta, e') = the iterate's angles and excesses, both weights 1. That objective is convex in
    (alpha, e) and the start is its unconstrained minimum, so IPOPT converges like an angle mode
    from a near start (docs/tuning.md, "projection_iterations"). Run with the angle modes' small
    initial barrier and at most ``settings.projection_iterations`` iterations. ``excess_band``
    (lower, upper), optional: bounds on log e kept too (see :func:`solve_angles`).

    Returns
    -------
    IpoptRun
        The run, named "projection" (recorded in ``stages`` if given).
    """
    angles, excess = nlp.unpack(x)
    here = replace(targets, angles=angles, excess=excess, angle_weight=1.0, area_weight=1.0,
                   corner_weighting="uniform")
    projection = AngleNLP(connectivity, here, formulation, dropped_vertices=dropped,
                          obtuse_corners=angles > settings.obtuse_angle, angle_margin=settings.angle_margin,
                          dropped_penalty=settings.dropped_penalty)
    projection_options = dict(options, **settings.angle_mode_margin_options)
    projection_options["max_iter"] = settings.projection_iterations
    t = len(excess)
    log_e = x[3 * t:]
    return run_ipopt(projection, "projection", x, settings, stages, inequalities=True, options=projection_options,
                     progress=progress, excess_bounds=within_band(log_e - excess_window, log_e + excess_window,
                                                                  excess_band),
                     log_u_lower=log_u_lower)


def _stage_record(name, run):
    """The statistics of one IPOPT run kept in the result."""
    return dict(name=name, status=run.status, iterations=run.iterations, objective=run.objective,
                time_s=run.time_s, build_s=run.build_s)


def _floor_counts(context, angles, excess):
    """Corners at, below or within 1% of their floors (context.log_u_floor), triangles within 1% of
    theirs (context.log_e_floor): a triangle the start had below it keeps its own size as bound
    (``max_floor_lift``) and is not on the floor."""
    with np.errstate(divide="ignore", invalid="ignore"):
        log_e = np.log(excess)
        return (int(np.sum(_log_u(angles, excess) <= context.log_u_floor + 0.01)),
                int(np.sum((log_e <= context.log_e_floor + 0.01) & (log_e >= context.log_e_floor - 0.01))))


def _solution(context, angles, excess, run, stopped_status=None):
    """The AngleSolution of the last run; ``stopped_status``: the run is the projection of a stage
    that IPOPT stopped with that status (see :func:`project_onto_constraints`)."""
    violation = max_constraint_violation(context.connectivity, angles, excess)
    success = bool(run.success and not violates_inequalities(angles, excess)
                   and violation <= context.settings.feasibility_tolerance)
    initial = context.initial
    floor_corners = floor_triangles = 0
    if context.formulation == "log-chord":
        floor_corners, floor_triangles = _floor_counts(context, angles, excess)
    return AngleSolution(angles=angles, excess=excess, success=success,
                         floor_corners=floor_corners, floor_triangles=floor_triangles,
                         status=stopped_status or run.status, converged=success and stopped_status is None,
                         iterations=sum(s["iterations"] for s in context.stages),
                         objective=objective_value(context.targets, angles, excess),
                         max_constraint_violation=violation, stages=context.stages,
                         initial_angles=initial.angles, initial_excess=initial.excess, start=initial.kind)
