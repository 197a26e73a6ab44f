"""Solve for the spherical angles.

``log-chord`` (default): start from a valid spherical triangulation of the mesh
(:func:`starting_positions`: the conformal map, repaired if needed, else the convex embedding),
whose angles satisfy every constraint; the inequalities (3)-(5) hold by construction in that
formulation, and the three redundant vertex constraints are left out (see
:class:`sphere_nlp.nlp.AngleNLP`). Stages:

1. Area modes only (area weight > 0): :func:`area_continuation` walks the excesses from the start's
   to the targets with a log-area objective, so that the next stage starts near its optimum.
2. "margin": IPOPT on the objective (9) and the equalities with every u = alpha - e/2 kept >= a
   margin (corners already below it at the start: >= their own size less 10%, see
   :func:`margin_restart`), inside a trust region on the log excesses (a window of
   +-ANGLE_MODE_EXCESS_WINDOW, area modes +-EXCESS_WINDOW, around the start); re-centred,
   warm-started and with a window twice as wide each time its result touches the window. The
   paper adds its inequalities only when the equality solution breaks them, but here they cost
   little (in log u they are simple bounds, mostly far from active) and the optimum is often at a
   degenerate triangle, which an equality stage chases towards log u = -inf (see
   :data:`ANGLE_MODE_EXCESS_WINDOW` for the iterations this saves).
3. Only if that run diverged (left the solution set): "equality", the same without the margin, then
   "margin" again from its result, or from the start if that diverged too.
4. "penalty-1e+04", "penalty-1e+06", only if the left-out vertex sums did not come back: again
   from there with their penalty 100 and then 10,000 times stiffer.
5. "all-constraints", only if they still did not: from the start with all of (7).

``faithful`` and ``substituted``: staged as in section 4 of the paper:

1. A linear least-squares start: the point closest to the targets (beta, e') that satisfies the linear
   constraints (6) and (7) exactly.
2. IPOPT with the equality constraints only.
3. Only if the result has a non-positive angle or excess, or e >= 2 alpha somewhere, IPOPT again with
   the inequalities (3)-(5) added, warm-started from stage 2.

Plain numpy in and out; CasADi stays in :mod:`sphere_nlp.nlp`.
"""

from dataclasses import dataclass, field, replace
from fractions import Fraction

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from . import interrupts
from .nlp import DEFAULT_FORMULATION, DROPPED_PENALTY, AngleNLP

DEFAULT_IPOPT_OPTIONS = {
    "tol": 1e-8,
    # IPOPT's default (1e-4) is far too loose: the unfolding needs the edge lengths to agree.
    "constr_viol_tol": 1e-10,
    "max_iter": 3000,
    "print_level": 0,
    "sb": "yes",
    # Keep bounds exact: with the default relaxation an angle bounded by 0 can end slightly negative.
    "bound_relax_factor": 0.0,
    # AMD ordering for MUMPS. MUMPS's automatic choice fills in badly on these KKT systems
    # (10,242 vertices: 3 iterations took 243 s), and so does AMF (armadillo_remeshed.obj: 56 s
    # for the 7 iterations that take 6 s now). AMD against METIS, measured with MC64 off (below):
    # linear-solver CPU -37% on armadillo_remeshed, -25% on armadillo.obj, -35% on nefertiti.obj
    # (whole run 128 -> 101 s, peak RSS 2.18 -> 1.92 GB), -21% on the Loop armadillo (173k
    # vertices, RSS 4.9 -> 4.4 GB); the angle modes take the same iterations to the same optima.
    "mumps_pivot_order": 0,
    # No MC64 matching and no scaling in MUMPS: with the automatic choice (7 and 77) the analysis
    # used the first matrix's values, and a warm-started margin stage spent 64 of its 103 s there
    # (nefertiti.obj; 1.9 s now). Same iterations and optima on every row measured; time
    # cheburashka 37 -> 21 s, armadillo_remeshed 12.5 -> 7.5 s, armadillo.obj 46 -> 38 s. The
    # iterative scaling then used (8) cost 8% of a solve (armadillo.obj profile): without it the
    # search directions took 11.3-12.9 s against 14.5-15.8 s (armadillo.obj, alternating runs),
    # nefertiti.obj 89.6 -> 75.6 s back to back; same iterations and optima in the angle modes,
    # area modes the same optima in +-10% iterations (hand_closed.obj original-areas 311 -> 293).
    "mumps_permuting_scaling": 0,
    "mumps_scaling": 0,
    # IPOPT's default refines every search direction at least once; MUMPS's solves are accurate
    # enough here that refining only when the residual asks for it cuts the back-solve time by a
    # third or more (armadillo.obj original-angles: 3.9 -> 2.1-2.5 s, search directions 11.2-11.9
    # -> 8.7-10.3 s in alternating runs; the Loop armadillo: no measurable change either way) with
    # the same iterations and optima in the angle modes (nefertiti, max_planck, cheburashka,
    # knight); area modes nearby optima (knight original-areas 180 -> 169 iterations, objective
    # 21.2298 -> 20.7137).
    "min_refinement_steps": 0,
    # The filter's cap on the constraint violation (1-norm), theta_max_fact * max(1, start's): at
    # IPOPT's default (1e4) one full step took armadillo_remeshed.obj original-areas' margin stage
    # from max violation 0.07 to 5.5, past sin(alpha) = 0 (evaluation errors), and it never came
    # back (restoration failed; the last-resort solve ran for over half an hour). With 10 that
    # stage certified (614 iterations); on the angle-mode benchmark rows it changed iterations by
    # -3..+5, to the same optima.
    "theta_max_fact": 10.0,
}

# The area modes measure that cap in the max-norm and set it to the start's violation (or 1): in
# the 1-norm, summed over 10^4-10^5 constraints, it let single vertex sums go off by pi
# (hand_closed.obj original-areas: the margin stage ended at max violation 5.45, and no later
# stage recovered; with these options it certified in 528 iterations).
AREA_MODE_IPOPT_OPTIONS = {
    "constraint_violation_norm_type": "max-norm",
    "theta_max_fact": 1.0,
}

# The angle modes' margin stage starts at the feasible start with a small barrier parameter: its
# bounds are far from most corners (in log u), and IPOPT's default mu_init (0.1) spent its first
# iterations pushing into the interior and back (knight original-angles 40 -> 37 iterations,
# nefertiti 37 -> 32, with windows of 5; the same optima).
ANGLE_MODE_MARGIN_OPTIONS = {"mu_init": 1e-6}

# Warm start of the inequality stage from the equality solution: start the barrier small and
# move the start only a little into the interior, so IPOPT stays near the equality optimum.
WARM_START_OPTIONS = {
    "warm_start_init_point": "yes",
    "mu_init": 1e-6,
    "warm_start_bound_push": 1e-9,
    "warm_start_bound_frac": 1e-9,
    "warm_start_slack_bound_push": 1e-9,
    "warm_start_slack_bound_frac": 1e-9,
    "warm_start_mult_bound_push": 1e-9,
}


# Trust region of the log-chord solve: each IPOPT run keeps every log e within this of where it
# started (a factor e^5 ~ 150 in area), re-centred up to MAX_WINDOW_ROUNDS times if it ends on it.
# 2.5 was needed before the obtuse form of (8) and the excess gauge; with them, 5 against 2.5
# (iterations): nefertiti 57 -> 35, knight 76 -> 47, cheburashka 78 -> 63, spot equal-angles
# 39 -> 26, bunny equal-angles 40 -> 23, brain equal-angles 48 -> 34, armadillo_remeshed
# equal-angles 13 -> 9, hand 9 -> 7, max_planck 34 -> 47, armadillo.obj 11 -> 11, all to the same
# optima; the area modes' six small rows 967 -> 970 in all. (10: spot, bunny, hand fewer still,
# knight, cheburashka, brain more: 264 on those six against 240.)
EXCESS_WINDOW = 5.0
# The angle modes' window, now that they go straight to the margin stage (below): against the
# equality stage followed by the margin stage with windows of 5 (iterations, all to the same
# optima): original-angles knight 47 -> 30, spot 13 -> 9, bunny 7 -> 7, max_planck 47 -> 19,
# elephant 9 -> 6, cheburashka 63 -> 27, hand 7 -> 6, brain 8 -> 9, armadillo_remeshed 7 -> 6,
# armadillo.obj 11 -> 8, nefertiti 35 -> 24; equal-angles knight 51 -> 28, spot 26 -> 18, bunny
# 23 -> 21, brain 34 -> 33, armadillo_remeshed 9 -> 7, armadillo.obj 44 -> 28. Windows of 5 and 10
# in that margin-first path: 32 and 22 on nefertiti, 37 and 36 on knight, 59 and 46 on cheburashka
# (10: 314 on the 17 rows above, against 286); no window at all: nefertiti 31, cheburashka 23,
# knight 30, armadillo.obj 7.
ANGLE_MODE_EXCESS_WINDOW = 20.0
MAX_WINDOW_ROUNDS = 6
# Each re-centred run widens the window by this factor and is warm-started (multipliers kept, small
# barrier): a cold restart spent 50-60 iterations re-converging where the last run ended, and the
# optimum can lie far away (cheburashka.off: some log excesses move by 19; 289 iterations / 78 s
# with fixed windows and cold restarts, 94 / 32 s with both).
WINDOW_GROWTH = 2.0

# Area modes: the first phase moves every log excess by at most this per continuation step
# (see area_continuation; knight.off original-areas failed with one step of 25, solved with four).
AREA_CONTINUATION_STEP = 6.0
# ... and runs IPOPT for at most this many iterations per step: the steps only make a start, and
# solving each one fully cost more (bunny.off equal-areas: 2,665 iterations and 546 s in all, one
# step wandering for 2,057 of them) than capping them (269 iterations, 55 s, a lower optimum).
AREA_CONTINUATION_ITERATIONS = 30
# ... unless the step's run ends further than this from the solution set (max |residual| of its
# equalities): then the step is run again from there, up to AREA_CONTINUATION_EXTRA_RUNS times. On
# the Loop armadillo (173k vertices, original-areas, clipped Hessian) the last step ended at 1.09,
# the margin stage started from violation 3.2 and objective 1.5e6, and after 15 iterations it was
# still at 1.56. Steps ending above 0.2 are rare below 50k vertices (knight equal-areas, spot and
# bunny original-areas; see benchmarks/results.md, session 12).
AREA_CONTINUATION_VIOLATION = 0.2
AREA_CONTINUATION_EXTRA_RUNS = 3
# If a re-run ends no nearer than the run before it (or the step diverged), the step is tried again
# with half its length from the last point the walk reached, up to this many times in the whole walk:
# re-running from a point far from the solution set mostly drifted further (Loop armadillo
# original-areas, steps of 1/5: the last step ended at 0.76, its re-runs at 0.60 and 0.88; going on
# from there, the margin stage never got back). Halved, the walk went 4/5 -> 9/10 (0.46, re-run
# 0.095) on the same mesh, and in equal-areas (the last step ended at 0.995, 0.989, 6.3) 4/5 -> 9/10
# (0.004) -> 1 (0.32, re-run 0.019), the first walk to reach the targets at this size. With the
# floor below as well, original-areas reached them too (1 at 0.61, 2.8; 9/10 0.51, 0.074; 1 at
# 0.109). No smaller benchmark row halves.
AREA_CONTINUATION_HALVINGS = 3
# The walk's steps keep every corner u above the margin stage's margin (a corner already below it
# at the start: above its own start size, less 10%), with the barrier started small (IPOPT
# mu_init) so that it moves the other corners little. Without the floor the steps collapsed corners
# towards u = 0 (the Loop armadillo original-areas: 1e-8 rad after step 4/5, 1e-17 after 1),
# where (8) is ill-conditioned and which the margin stage must then keep as its own bounds. With it,
# armadillo.obj original-areas took 753 iterations (continuation 187, margin 566) to objective
# 689.70 against 879 (242, 637) to 695.11, in 20 minutes against 31, beside another job each;
# nefertiti.obj original-areas 429 against 528 (340.88 against 336.99); armadillo_remeshed
# original-areas 408 against 464 iterations (273.00 against 272.77); the 14 area-mode rows up to
# 10k vertices 2,488 iterations against 2,352, objectives either side (benchmarks/results.md,
# session 14). mu_init 0.1 (IPOPT's default) instead: armadillo_remeshed
# 535 iterations, its walk re-run and halved.
AREA_CONTINUATION_FLOOR = True
AREA_CONTINUATION_OPTIONS = {"mu_init": 1e-4}

# The margin stage lifts corners below the margin to it only if that changes none of them by more
# than this factor in log u (see margin_restart).
MAX_MARGIN_LIFT = 1.0

# If the left-out vertex sums have not come back, the penalty on them is raised 100-fold up to this.
MAX_DROPPED_PENALTY = 1e6

# A solve counts only if every equality constraint (6)-(8) holds to this, whatever IPOPT reports.
FEASIBILITY_TOLERANCE = 1e-8

# A run that ends with a larger violation than this has left the solution set (a vertex sum off by
# pi, say), which the penalty stages cannot repair from there; runs that merely stop short end
# far below it (hand_closed.obj equal-angles: 2.5e-3 before the penalty stages).
DIVERGED_VIOLATION = 0.1
# ... and a log-chord run is stopped once its violation has stayed above this for
# ABORT_ITERATIONS iterations in a row: none came back from there, and each spent its whole time
# limit (armadillo_remeshed.obj original-areas sat at violation pi, a vertex sum off by pi, for
# 30 minutes; hand_closed.obj original-areas at 5.5 for 10 minutes). Runs that succeed can pass 1 briefly
# (armadillo_remeshed.obj original-areas, the certified margin stage: 1.71 at iteration 360, below
# 0.3 ten iterations later), hence the long count.
ABORT_VIOLATION = 1.0
ABORT_ITERATIONS = 50

# The Hessian the area modes hand IPOPT (AngleNLP's ``hessian``): "clipped" leaves out the negative
# part of the diagonal term that the log unknowns add, which vanishes at the optima. With the exact
# Hessian their long middle stretch was a crawl: the Hessian was indefinite at every iterate, IPOPT
# shifted it by 1e-2..1e-1 times the identity and cut most steps (bunny.off equal-areas: lg(rg)
# -2.4..-1.2 on all but the last 4 of 88 margin iterations). Benchmark rows (benchmarks/results.md,
# iterations in all and objective, exact at e7cb095 -> clipped with the continuation's re-runs at
# a22c0ba; other local optima of a non-convex problem, lower on 10 of 16 rows): equal-areas
# knight 156 -> 174 (21.49 -> 22.01), spot 180 -> 118 (54.99 -> 54.53), bunny 178 -> 154
# (65.11 -> 64.72), max_planck 132 -> 150 (90.85 -> 90.67), cheburashka 229 -> 231
# (134.26 -> 134.80), hand 314 -> 258 (180.90 -> 180.08), brain 30 -> 30 (same),
# armadillo_remeshed 573 -> 310 (285.41 -> 285.38; its continuation ends at objective 351 instead
# of 13,310); original-areas knight 169 -> 169 (20.71 -> 20.68), spot 105 -> 117 (33.42 -> 33.69),
# bunny 144 -> 193 (34.95 -> 34.02), max_planck 121 -> 144 (24.89 -> 25.06), cheburashka
# 246 -> 227 (91.49 -> 88.21), hand 296 -> 287 (152.55 -> 148.11), brain 92 -> 100
# (60.88 -> 60.05), armadillo_remeshed 598 -> 464 (266.25 -> 272.77); 3,563 -> 3,126 in all. The
# gain grows with size: armadillo.obj (43k) equal-areas passed the exact Hessian's final objective
# (1,225.37 after 1,224 margin iterations, 90 minutes) at margin iteration 320, 13 minutes in. Its
# iterations are cheaper too (fewer trial factorizations for the inertia correction: 1.8 s against
# 3.8-4.4 s at 43k, each beside one other job).
AREA_MODE_HESSIAN = "clipped"

# What a margin stage stopped by the caller's limits yields (solve_angles's on_limit).
ON_LIMIT = ("fail", "project")
# IPOPT statuses of a run stopped short by the caller's limits (max_iter, max_time).
LIMIT_STATUSES = ("Maximum_Iterations_Exceeded", "Maximum_WallTime_Exceeded", "Maximum_CpuTime_Exceeded")
# With on_limit="project", a log-chord margin stage stopped by those limits is not wasted: its
# iterate, which can be well off the constraints (armadillo_remeshed.obj original-areas after 50,
# 100 and 150 of its 306 margin iterations: violation 0.36, 0.59, 0.05), is projected onto them
# (see project_onto_constraints) in 7, 6 and 4 IPOPT iterations, 2.4-3.4 s, changing the objective
# by < 0.1% (287.177 -> 287.115, 280.745 -> 280.692, 277.264 -> 277.238). The projection has its
# own iteration cap, this (max_iter does not apply to it; max_time does).
PROJECTION_ITERATIONS = 50
# The projection runs after the stage that reached max_time; with max_time bounding the whole run
# (interrupts.deadline), it may take this much more: a fifth of max_time plus 5 s.
PROJECTION_GRACE_FRACTION = 0.2
PROJECTION_GRACE_S = 5.0

# Corners above this angle at the start use the obtuse form of the edge constraints (AngleNLP).
OBTUSE_ANGLE = np.pi / 2


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
        (see :data:`ABORT_VIOLATION`).
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
        Which starting point: "conformal", "conformal-untangled", "embedding",
        "embedding-uncentred" or "linear".
    converged : bool
        True when the last stage reached IPOPT's optimality tolerance. False for a failed solve, and
        for a successful one whose margin stage stopped at ``max_iter`` or ``max_time``: its iterate
        projected onto the constraints (stage "projection"), feasible but not optimal; ``status``
        is then the stopped stage's (e.g. "Maximum_WallTime_Exceeded").
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
    converged: bool = False


def linear_initial_guess(connectivity, targets):
    """Closest point to (beta, e') satisfying (6) and (7) exactly, by a sparse least-squares solve.

    Minimises ||alpha - beta||^2 + ||e - e'||^2 subject to alpha0 + alpha1 + alpha2 - e = pi per
    triangle and the angle sum 2 pi at every vertex.

    Returns
    -------
    angles : (t, 3) array
    excess : (t,) array

    Examples
    --------
    >>> from sphere_nlp.shapes import tetrahedron
    >>> from sphere_nlp.connectivity import build_connectivity
    >>> from sphere_nlp.targets import make_targets
    >>> V, F = tetrahedron()
    >>> c = build_connectivity(F, 4)
    >>> angles, excess = linear_initial_guess(c, make_targets("original-angles", V, F, c.vertex_degree))
    >>> np.allclose(angles, 2 * np.pi / 3), np.allclose(excess, np.pi)
    (True, True)
    """
    t, n = connectivity.n_faces, connectivity.n_vertices
    triangle_sum = sp.csr_matrix((np.ones(3 * t), (np.repeat(np.arange(t), 3), np.arange(3 * t))),
                                 shape=(t, 3 * t))
    A = sp.vstack([sp.hstack([triangle_sum, -sp.identity(t)]),
                   sp.hstack([connectivity.vertex_corner_matrix(), sp.csr_matrix((n, t))])]).tocsr()
    b = np.concatenate([np.full(t, np.pi), np.full(n, 2 * np.pi)])
    x_target = np.concatenate([targets.angles.ravel(), targets.excess])
    # (6) and (7) are independent (summing (7) minus summing (6) leaves sum(e)), so A A^T is
    # positive definite and the minimum-norm correction is unique.
    y = spla.spsolve((A @ A.T).tocsc(), b - A @ x_target)
    x = x_target + A.T @ y
    return x[:3 * t].reshape(t, 3), x[3 * t:]


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
    # (sin B sin C), which exceeded FEASIBILITY_TOLERANCE at a sliver with two corners at the
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
    """Objective (9) with the weights and scaling of :mod:`sphere_nlp.targets`."""
    return float(targets.angle_weight * np.sum((angles - targets.angles) ** 2)
                 + targets.area_weight * np.sum(((excess - targets.excess) / targets.excess_scale) ** 2))


def independent_vertices(positions):
    """Three vertices whose positions are as close to orthonormal as the mesh allows."""
    first = int(np.argmax(positions[:, 2]))
    second = int(np.argmin(np.abs(positions @ positions[first])))
    normal = np.cross(positions[first], positions[second])
    third = int(np.argmax(np.abs(positions @ normal)))
    return [first, second, third]


START_POINTS = ("auto", "conformal", "embedding", "linear")

# Mobius normalisation of the angle modes' start (see starting_positions). "excess" moves the start
# to the optimum's normalisation: nefertiti.obj's first run spent 150 s (55 iterations, not
# converged) moving 78% of the log excesses by > 1 along a nearly flat Mobius direction (a dipole of
# size 2.1). It was not the default while the edge constraints of obtuse corners were ill-conditioned
# (cheburashka 94 -> 274 iterations, max_planck 102 -> 122, nefertiti's equality stage stalled);
# with their obtuse form (AngleNLP), against the "area" gauge: nefertiti 93 -> 69 iterations (same
# objective 207.133106), elephant 24 -> 10, hand 14 -> 9, armadillo_remeshed 14 -> 9, brain 11 -> 9,
# bunny 13 -> 10, knight 83 -> 80, max_planck 37 -> 35, spot 12 -> 12, cheburashka 72 -> 80;
# equal-angles spot and bunny 53 -> 44, armadillo_remeshed 25 -> 13; armadillo.obj 15 -> 11. The area
# modes keep the area gauge (their continuation sets the scale).
START_GAUGE = "excess"


def starting_positions(connectivity, vertices=None, kind="auto", gauge="area"):
    """Valid spherical positions of the mesh to start the log-chord solve from.

    ``"conformal"``: the linear spherical conformal map (:func:`sphere_nlp.baselines.conformal_map`),
    Mobius-centred by vertex area. Close to the optimum of every angle mode (brain, 10,242 vertices,
    original-angles: 7 iterations instead of > 330 s from the embedding), but not always bijective.
    ``"embedding"``: the convex embedding (:func:`sphere_nlp.embedding.convex_embedding`), valid by
    construction, Mobius-centred when that keeps it valid. ``"auto"``: the conformal map if it
    certifies, else the conformal map with its flipped triangles repaired by
    :func:`sphere_nlp.untangle.untangle` if that certifies, else the embedding.

    ``gauge="excess"`` then moves the start by the Mobius transformation minimising the sum of
    squared excesses (:func:`sphere_nlp.embedding.excess_gauge`), the normalisation of the angle
    modes' optimum (kept only if it certifies); ``"area"`` (default) keeps the area centring.

    Returns
    -------
    positions : (n, 3) array of unit vectors, a certified spherical triangulation
    kind : str
        Which start was used: "conformal", "conformal-untangled", "embedding" or
        "embedding-uncentred".
    """
    positions, kind = _area_centred_start(connectivity, vertices, kind)
    if gauge == "excess":
        from .certify import certify
        from .embedding import excess_gauge
        moved = excess_gauge(positions, connectivity.faces)
        if moved is not positions and certify(moved, connectivity.faces).valid:
            return moved, kind
    return positions, kind


def _area_centred_start(connectivity, vertices, kind):
    """:func:`starting_positions` with the area-centred gauge."""
    from .certify import certify
    from .embedding import convex_embedding, mobius_centre

    faces = connectivity.faces
    weights = None
    if vertices is not None:
        from .targets import triangle_areas_3d
        weights = np.bincount(faces.ravel(), np.repeat(triangle_areas_3d(vertices, faces), 3),
                              minlength=connectivity.n_vertices)
    if kind in ("auto", "conformal") and vertices is not None:
        from .baselines import conformal_map
        with np.errstate(all="ignore"):
            positions = mobius_centre(conformal_map(vertices, faces), weights)
        if np.isfinite(positions).all():
            if certify(positions, faces).valid:
                return positions, "conformal"
            # A few flipped triangles (knight 57, cheburashka 38, max_planck 2, nefertiti 1):
            # re-embed small disks around them, which keeps the map conformal elsewhere.
            from .untangle import untangle
            repaired, _ = untangle(positions, faces, mesh_vertices=vertices)
            if repaired is not None and certify(repaired, faces).valid:
                return repaired, "conformal-untangled"
    positions = convex_embedding(connectivity, vertices, weights="uniform")
    centred = mobius_centre(positions, weights)
    if certify(centred, faces).valid:
        return centred, "embedding"
    return positions, "embedding-uncentred"


def _checked_start_positions(connectivity, positions):
    """``positions`` as a float array if they are a certified spherical triangulation of the mesh,
    else UsageError naming what is wrong."""
    from .certify import certify
    from .errors import UsageError

    positions = np.asarray(positions, dtype=float)
    if positions.shape != (connectivity.n_vertices, 3):
        raise UsageError("start positions must be a (%d, 3) array, not %s"
                         % (connectivity.n_vertices, positions.shape))
    certificate = certify(positions, connectivity.faces)
    if not certificate.valid:
        raise UsageError("start positions are not a valid spherical map of the mesh: " + certificate.reason)
    return positions


def _angles_and_excess(positions, faces):
    """Corner angles (t, 3) and excesses (t,) of a valid spherical triangulation."""
    from .certify import signed_solid_angles, spherical_angles

    return spherical_angles(positions, faces), signed_solid_angles(positions, faces)


def feasible_start(connectivity, vertices=None, kind="auto", gauge="area"):
    """Angles and excesses of a valid spherical triangulation of the mesh, and its positions.

    See :func:`starting_positions` for ``kind``.

    Returns
    -------
    angles : (t, 3) array
    excess : (t,) array
    positions : (n, 3) array
    kind : str
    """
    positions, kind = starting_positions(connectivity, vertices, kind, gauge)
    return (*_angles_and_excess(positions, connectivity.faces), positions, kind)


def solve_angles(connectivity, targets, formulation=DEFAULT_FORMULATION, ipopt_options=None,
                 max_iter=None, max_time=None, progress=None, vertices=None, start=None, on_limit="fail"):
    """Solve the angle NLP (see the module docstring for the strategy of each formulation).

    Parameters
    ----------
    connectivity : Connectivity
    targets : Targets
    formulation : {"log-chord", "substituted", "faithful"}
    ipopt_options : dict, optional
        Extra IPOPT options, overriding :data:`DEFAULT_IPOPT_OPTIONS`.
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
        Starting point: the angles of a valid spherical triangulation (see
        :func:`starting_positions`), or the paper's linear least-squares start. Default "auto"
        for log-chord, "linear" for the paper's forms. An array is a certified spherical
        triangulation of the mesh to start from (unit vectors, ``connectivity``'s numbering), for
        instance a coarser mesh's solution carried over (:mod:`sphere_nlp.hierarchy`).

    Returns
    -------
    AngleSolution
    """
    if on_limit not in ON_LIMIT:
        raise ValueError("on_limit must be one of %s, not %r" % (ON_LIMIT, on_limit))
    options = dict(DEFAULT_IPOPT_OPTIONS)
    if targets.area_weight > 0 and formulation == "log-chord":
        options.update(AREA_MODE_IPOPT_OPTIONS)
    if max_iter is not None:
        options["max_iter"] = int(max_iter)
    if max_time is not None:
        options["max_wall_time"] = float(max_time)
    options.update(ipopt_options or {})
    # Warm-started runs: small barrier and bound pushes, but the caller's options still win.
    warm_options = dict(options, **WARM_START_OPTIONS)
    warm_options.update(ipopt_options or {})

    def stage_progress(name):
        if progress is None:
            return None
        return lambda it, f, viol, elapsed: progress(name, it, f, viol, elapsed)

    stages = []
    if start is None:
        start = "auto" if formulation == "log-chord" else "linear"
    given_positions = None
    if not isinstance(start, str):
        given_positions, start = _checked_start_positions(connectivity, start), "given"
    elif start not in START_POINTS:
        raise ValueError("start must be one of %s" % (START_POINTS,))
    if given_positions is not None:
        init_angles, init_excess = _angles_and_excess(given_positions, connectivity.faces)
        start_positions, start_kind = given_positions, "given"
    elif start == "linear":
        init_angles, init_excess = linear_initial_guess(connectivity, targets)
        start_kind = "linear"
    else:
        gauge = START_GAUGE if targets.area_weight == 0 else "area"
        init_angles, init_excess, start_positions, start_kind = feasible_start(connectivity, vertices, start,
                                                                               gauge)
    if formulation == "log-chord":
        dropped = independent_vertices(start_positions) if start != "linear" else []
        # Corners obtuse at the start get the well-conditioned form of (8) near pi (AngleNLP).
        obtuse = init_angles > OBTUSE_ANGLE
        # The area modes hand IPOPT the clipped Hessian (see AREA_MODE_HESSIAN); the angle modes the exact one.
        hessian = AREA_MODE_HESSIAN if targets.area_weight > 0 else "exact"
        nlp = AngleNLP(connectivity, targets, formulation, dropped_vertices=dropped, obtuse_corners=obtuse,
                       hessian=hessian)
        t = connectivity.n_faces
        x0 = nlp.pack(init_angles, init_excess)

        def obtuse_at(x):
            return nlp.unpack(x)[0] > OBTUSE_ANGLE

        mode_window = EXCESS_WINDOW if targets.area_weight > 0 else ANGLE_MODE_EXCESS_WINDOW

        def windowed_solve(x_start, name, inequalities=False, recentre=True, log_u_lower=None,
                           warm_from=None, first_options=None):
            # Bounds log e within mode_window of the current point act as a trust region: when most
            # triangles are tiny, scaling all their excesses together barely changes (6)-(8) and, in
            # the angle modes, not the objective either, so IPOPT took huge steps along that flat
            # direction (armadillo.obj, 43k vertices: diverged; with the window 17 iterations). The
            # barrier terms also convexify it. If the result touches the window, re-centre and repeat
            # (if recentre), else report it as touched (run["touched"]). warm_from: an earlier run
            # with the same equality constraints whose multipliers start this one.
            x, window, previous = x_start, mode_window, warm_from
            for round_ in range(MAX_WINDOW_ROUNDS):
                log_e = x[3 * t:]
                run_options, warm = first_options or options, {}
                if previous is not None:
                    run_options = warm_options
                    lam_x = previous["lam_x"].copy()
                    lam_x[3 * t:] = 0.0               # the old window's bounds are gone
                    warm = dict(lam_g0=previous["lam_g"], lam_x0=lam_x)
                run = nlp.solve(x, inequalities=inequalities, options=run_options,
                                progress=stage_progress(name),
                                excess_bounds=(log_e - window, log_e + window), log_u_lower=log_u_lower,
                                abort_violation=ABORT_VIOLATION, abort_iterations=ABORT_ITERATIONS,
                                **warm)
                stages.append(_stage_record(name if round_ == 0 else "%s-recentred" % name, run))
                moved = np.max(np.abs(run["x"][3 * t:] - log_e), initial=0.0)
                run["touched"] = bool(moved >= 0.99 * window)
                if not run["success"] or not np.isfinite(run["x"]).all() or not run["touched"] or not recentre:
                    return run
                x, previous = run["x"], run
                window *= WINDOW_GROWTH
            return run

        x_start = x0
        if targets.area_weight > 0:
            # Each step, and the stages after the walk, flag the corners obtuse at their own start:
            # the areas reshape the triangles.
            x_start = area_continuation(nlp_for=lambda tg, x: AngleNLP(connectivity, tg, formulation,
                                                                       dropped_vertices=dropped,
                                                                       area_form="log",
                                                                       obtuse_corners=obtuse_at(x),
                                                                       hessian=hessian),
                                        targets=targets, x0=x0, n_faces=t, options=options,
                                        progress=stage_progress("area-continuation"), stages=stages)
            obtuse = obtuse_at(x_start)
            nlp = AngleNLP(connectivity, targets, formulation, dropped_vertices=dropped,
                           obtuse_corners=obtuse, hessian=hessian)
        # Straight to the margin stage: the optimum is often at a degenerate triangle (area modes
        # nearly always), which an equality stage chases towards log u = -inf before the margin
        # stage starts again anyway (armadillo_remeshed.obj equal-areas: 667 equality + 627 margin
        # iterations, now 638; knight.off original-areas 1,443 iterations in all, now 188;
        # nefertiti.obj original-angles 21 + 14, now 24; see ANGLE_MODE_EXCESS_WINDOW).
        first_options = None
        if targets.area_weight == 0:
            first_options = dict(options, **ANGLE_MODE_MARGIN_OPTIONS)
            first_options.update(ipopt_options or {})
        restart, log_u_lower, _ = margin_restart(x_start, x_start, t, nlp.angle_margin)
        direct = windowed_solve(restart, "margin", inequalities=True, log_u_lower=log_u_lower,
                                first_options=first_options)
        if on_limit == "project" and direct["status"] in LIMIT_STATUSES and np.isfinite(direct["x"]).all():
            # Stopped by the caller's limits: hand back its iterate made feasible, if that works.
            # Past a run's deadline (interrupts.deadline) the projection gets its own short grace.
            grace = PROJECTION_GRACE_FRACTION * (max_time or 0.0) + PROJECTION_GRACE_S
            with interrupts.extended_deadline(grace):
                projection = project_onto_constraints(connectivity, targets, nlp, direct["x"], formulation,
                                                      dropped, options, log_u_lower, mode_window,
                                                      progress=stage_progress("projection"))
            stages.append(_stage_record("projection", projection))
            projected = _finish(connectivity, targets, *nlp.unpack(projection["x"]), projection, stages,
                                init_angles, init_excess, start_kind, stopped_status=direct["status"])
            if projected.success:
                return projected
        if interrupts.deadline_passed():
            # The run's time is up (interrupts.deadline): no fallback stage, each would be built
            # only to stop at once (bipyramid(1000): 6.7 s of building after the limit).
            return _finish(connectivity, targets, *nlp.unpack(direct["x"]), direct, stages, init_angles,
                           init_excess, start_kind)
        run, with_margin = direct, True
        if _diverged(connectivity, nlp, direct["x"]):
            # The direct margin stage ran away from the solution set (hand_closed.obj
            # original-areas: violation 5.5): the equality stage first.
            # It gets one window: a run that ends on it is continued by the margin stage instead
            # of being re-centred, because the triangles that pull it are often degenerating
            # slivers (max_planck.obj: 4 re-centred equality runs, 534 iterations, chased two
            # corners of 0.12-1 deg slivers down to 1e-7 rad and ended in Restoration_Failed; the
            # margin stage then needed 433 more; now 38 + 64 in all).
            run = windowed_solve(x_start, "equality", recentre=False)
            with_margin, log_u_lower = False, None
            equality_diverged = _diverged(connectivity, nlp, run["x"])
            if (not run["success"] or run["touched"] or equality_diverged
                    or not np.min(run["x"][:3 * t]) > np.log(nlp.angle_margin)):
                # The optimum lies at (or the solver ran into) a degenerate triangle, or further
                # than the window: solve again with u >= angle_margin, from the equality result
                # if it is usable (not diverged; its corners can look fine even then), else from
                # the feasible start x0 (in the angle modes x_start is x0; the continuation's end
                # is known to fail). The equality result is used however far its corners are
                # below the margin: they keep their own size, less 10%, as bound (see
                # margin_restart).
                x_equality = x0 if equality_diverged else run["x"]
                restart, log_u_lower, from_equality = margin_restart(x_equality, x0, t, nlp.angle_margin,
                                                                     np.inf)
                # From the equality result, warm-started with its multipliers (same equalities):
                # a cold start's bound push broke (8) by 0.02-0.5 there (nefertiti.obj), and the
                # barrier then had to shrink again (knight 22 -> 18 margin iterations, spot
                # equal-angles 14 -> 9, brain equal-angles 10 -> 6, same optima).
                run = windowed_solve(restart, "margin", inequalities=True, log_u_lower=log_u_lower,
                                     warm_from=run if from_equality else None)
                with_margin = True
        penalty = DROPPED_PENALTY
        violation = max_constraint_violation(connectivity, *nlp.unpack(run["x"]))
        while violation > FEASIBILITY_TOLERANCE and np.isfinite(run["x"]).all() and penalty < MAX_DROPPED_PENALTY:
            # The three left-out vertex sums come back by themselves only near the solution set
            # (the redundancy is infinitesimal); with a weak penalty the solver can stop at a metric
            # whose sums are off there (hand_closed.obj equal-angles: by 2.5e-3). A stiffer penalty,
            # from that point, pulls them back (hand: 1e6 gave 1e-13, 47 s in all, where the
            # all-constraints solve below had not finished in 15 minutes).
            penalty *= 100
            nlp = AngleNLP(connectivity, targets, formulation, dropped_vertices=dropped,
                           dropped_penalty=penalty, obtuse_corners=obtuse, hessian=hessian)
            run = windowed_solve(run["x"], "penalty-%.0e" % penalty, inequalities=with_margin,
                                 log_u_lower=log_u_lower)
            violation = max_constraint_violation(connectivity, *nlp.unpack(run["x"]))
        if violation > FEASIBILITY_TOLERANCE:
            # Last resort: every constraint (a singular Jacobian at the solution, so slow).
            nlp = AngleNLP(connectivity, targets, formulation, obtuse_corners=obtuse, hessian=hessian)
            run = windowed_solve(x_start, "all-constraints")
        angles, excess = nlp.unpack(run["x"])
        return _finish(connectivity, targets, angles, excess, run, stages, init_angles, init_excess, start_kind)

    nlp = AngleNLP(connectivity, targets, formulation)
    run = nlp.solve(nlp.pack(init_angles, init_excess), inequalities=False, options=options,
                    progress=stage_progress("equality"))
    stages.append(_stage_record("equality", run))
    angles, excess = nlp.unpack(run["x"])
    if violates_inequalities(angles, excess):
        run = nlp.solve(run["x"], inequalities=True, lam_g0=run["lam_g"], options=warm_options,
                        progress=stage_progress("inequality"))
        if not run["success"]:
            # A warm start from an infeasible point can stall; a cold start with the default barrier
            # parameter is slower but robust.
            cold = dict(options)
            run = nlp.solve(nlp.pack(init_angles, init_excess), inequalities=True, options=cold,
                            progress=stage_progress("inequality-cold"))
        stages.append(_stage_record("inequality", run))
        angles, excess = nlp.unpack(run["x"])
    return _finish(connectivity, targets, angles, excess, run, stages, init_angles, init_excess, start_kind)


def _diverged(connectivity, nlp, x):
    """Whether a run ended far from the solution set (not merely short of the tolerance)."""
    if not np.isfinite(x).all():
        return True
    return max_constraint_violation(connectivity, *nlp.unpack(x)) > DIVERGED_VIOLATION


def margin_restart(x_equality, x_start, n_faces, angle_margin, max_lift=MAX_MARGIN_LIFT):
    """Where the margin stage starts, and its lower bounds on log u per corner.

    From the equality stage's result if it is finite and lifting its corners to the margin changes
    none by more than a factor exp(max_lift) (corners already below the margin at the start: none
    below their start size by more), else from the stage's own start: a corner the equality stage drove
    far below the margin (armadillo_remeshed.obj equal-areas: u = 1e-8), lifted to it, broke (8) by
    ~7, the margin stage failed and the last-resort solve ran for over an hour. Corners of that
    start which are themselves below the margin (nefertiti.obj's start in the excess gauge has a
    180-degree triangle with corners of 6e-7 rad) keep their own size, less 10%, as their bound;
    so do the equality result's with ``max_lift=inf`` (used once the stage's start is known to fail).

    Returns
    -------
    restart : array
        A copy, with corners just inside their bounds.
    log_u_lower : (3 n_faces,) array
    from_equality : bool
        Whether ``restart`` is the equality result (else the stage's start).
    """
    margin = np.log(angle_margin)
    restart = x_start
    # A corner already below the margin at the start counts from its own size there: nefertiti.obj
    # has two of 6e-7 rad, which grew to 7e-6 in the equality stage; measured from the margin they
    # sent the margin stage back to the start (14 iterations to regain the equality objective).
    floor = np.minimum(margin, x_start[:3 * n_faces])
    from_equality = bool(np.isfinite(x_equality).all()
                         and np.all(x_equality[:3 * n_faces] > floor - max_lift))
    restart = np.array(x_equality if from_equality else x_start, float)
    log_u = restart[:3 * n_faces]
    log_u_lower = np.where(log_u < margin - MAX_MARGIN_LIFT, log_u - 0.1, margin)
    restart[:3 * n_faces] = np.maximum(log_u, log_u_lower + 1e-3)
    return restart, log_u_lower, from_equality


def area_continuation(nlp_for, targets, x0, n_faces, options, progress=None, stages=None):
    """Walk the log excesses from the start's to the targets' (the area modes' first phase).

    The start (a conformal map) can be far from the area targets: on knight.off some log excesses
    must change by 25. With the objective (9) the pull on a tiny triangle's log excess vanishes
    with its size (d/ds (e^s - e')^2 = 2 e (e - e')) and is non-convex in s, so IPOPT crawled
    (bunny.off original-areas: no result in 120 s) or diverged. This phase instead minimises the
    same weighted sum with the area term (log e - log e'_tau)^2, convex in s with a pull that does
    not fade, for targets e'_tau that move from the start's excesses to e' geometrically in steps
    of at most :data:`AREA_CONTINUATION_STEP` per log excess, each with at most
    :data:`AREA_CONTINUATION_ITERATIONS` IPOPT iterations: the point only has to be a good start
    for (9), which the caller then solves from it. A step whose run ends far from the solution set
    (:data:`AREA_CONTINUATION_VIOLATION`) is re-run from where it ended, and if that gets no nearer,
    tried again at half the length from the last point reached (:data:`AREA_CONTINUATION_HALVINGS`).
    The steps keep the corners above a floor (:func:`continuation_floor`); they are named by
    their fraction of the way ("area-continuation-3/4", "-more1" for a re-run).

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

    Returns
    -------
    x : array
        The last finite point reached (x0 if the first step diverges); it may be slightly
        infeasible when a step was capped.
    """
    start_log = x0[3 * n_faces:]
    target_log = np.log(targets.excess)
    n_steps = max(1, int(np.ceil(np.max(np.abs(target_log - start_log)) / AREA_CONTINUATION_STEP)))
    # Only a start is needed, so each step is capped (the last iterations of a step refine the
    # weak angle term and are repeated by the next step anyway).
    capped = dict(options, max_iter=min(int(options.get("max_iter", 3000)), AREA_CONTINUATION_ITERATIONS))
    # Exact fractions, so that tau = k / n_steps exactly when no step was halved.
    x, reached, step, halvings = x0, Fraction(0), Fraction(1, n_steps), 0

    def violation(nlp, run):
        if not np.isfinite(run["x"]).all():
            return np.inf
        return np.max(np.abs(nlp.evaluate(run["x"])[1]))

    while reached < 1:
        tau = min(reached + step, Fraction(1))
        excess = np.exp((1 - float(tau)) * start_log + float(tau) * target_log)
        nlp = nlp_for(replace(targets, excess=excess * (4 * np.pi / excess.sum())), x)
        floor, step_options = {}, capped
        if AREA_CONTINUATION_FLOOR:
            floor = dict(inequalities=True, log_u_lower=continuation_floor(x0, n_faces, nlp.angle_margin))
            step_options = dict(capped, **AREA_CONTINUATION_OPTIONS)
        name = "area-continuation-%s" % tau
        run = nlp.solve(x, options=step_options, progress=progress, **floor)
        if stages is not None:
            stages.append(_stage_record(name, run))
        ended = violation(nlp, run)
        for attempt in range(1, AREA_CONTINUATION_EXTRA_RUNS + 1):
            if not AREA_CONTINUATION_VIOLATION < ended < np.inf:
                break
            rerun = nlp.solve(run["x"], options=step_options, progress=progress, **floor)
            if stages is not None:
                stages.append(_stage_record("%s-more%d" % (name, attempt), rerun))
            rerun_ended = violation(nlp, rerun)
            if rerun_ended >= ended and halvings < AREA_CONTINUATION_HALVINGS:
                break                           # drifting away: halve the step instead
            run, ended = rerun, rerun_ended
        if ended > AREA_CONTINUATION_VIOLATION and halvings < AREA_CONTINUATION_HALVINGS:
            # A nearer target, from the last good point: going on from a point far from the
            # solution set only drifted further (see AREA_CONTINUATION_HALVINGS).
            halvings, step = halvings + 1, step / 2
            continue
        if ended == np.inf:
            break
        x, reached = run["x"], tau
    return x


def continuation_floor(x0, n_faces, angle_margin):
    """Lower bounds on log u for the area continuation's steps (see :data:`AREA_CONTINUATION_FLOOR`).

    ``log(angle_margin)`` for every corner, except those already below it at the start ``x0``,
    which may not shrink below their own start size less 10%.

    Examples
    --------
    >>> continuation_floor(np.log([1.0, 1e-6, 0.5, 1.0]), 1, 1e-4).round(2)
    array([ -9.21, -13.92,  -9.21])
    """
    margin = np.log(angle_margin)
    log_u = np.asarray(x0, float)[:3 * n_faces]
    return np.where(log_u < margin, log_u - 0.1, margin)


def project_onto_constraints(connectivity, targets, nlp, x, formulation, dropped, options, log_u_lower,
                             excess_window, progress=None):
    """The feasible point nearest a log-chord iterate ``x`` (a stage stopped short), by IPOPT.

    The same constraints and bounds (log u >= ``log_u_lower``, log e within ``excess_window`` of
    ``x``), with the objective (9) replaced by its value's distance from the iterate: targets
    (beta, e') = the iterate's angles and excesses, both weights 1. That objective is convex in
    (alpha, e) and the start is its unconstrained minimum, so IPOPT converges like an angle mode
    from a near start (see :data:`PROJECTION_ITERATIONS`). Run with the angle modes' small
    initial barrier and at most :data:`PROJECTION_ITERATIONS` iterations.

    Returns
    -------
    dict
        :meth:`sphere_nlp.nlp.AngleNLP.solve`'s result.
    """
    angles, excess = nlp.unpack(x)
    here = replace(targets, angles=angles, excess=excess, angle_weight=1.0, area_weight=1.0)
    projection = AngleNLP(connectivity, here, formulation, dropped_vertices=dropped,
                          obtuse_corners=angles > OBTUSE_ANGLE)
    projection_options = dict(options, **ANGLE_MODE_MARGIN_OPTIONS)
    projection_options["max_iter"] = PROJECTION_ITERATIONS
    t = len(excess)
    log_e = x[3 * t:]
    return projection.solve(x, inequalities=True, options=projection_options, progress=progress,
                            excess_bounds=(log_e - excess_window, log_e + excess_window),
                            log_u_lower=log_u_lower)


def _stage_record(name, run):
    """The statistics of one IPOPT run kept in the result."""
    return dict(name=name, **{k: run[k] for k in ("status", "iterations", "objective", "time_s", "build_s")})


def _finish(connectivity, targets, angles, excess, run, stages, init_angles, init_excess, start_kind,
            stopped_status=None):
    """The AngleSolution of the last run; ``stopped_status``: the run is the projection of a stage
    that IPOPT stopped with that status (see :func:`project_onto_constraints`)."""
    violation = max_constraint_violation(connectivity, angles, excess)
    success = bool(run["success"] and not violates_inequalities(angles, excess)
                   and violation <= FEASIBILITY_TOLERANCE)
    return AngleSolution(angles=angles, excess=excess, success=success,
                         status=stopped_status or run["status"], converged=success and stopped_status is None,
                         iterations=sum(s["iterations"] for s in stages),
                         objective=objective_value(targets, angles, excess),
                         max_constraint_violation=violation, stages=stages,
                         initial_angles=init_angles, initial_excess=init_excess, start=start_kind)
