"""Solve for the spherical angles.

``log-chord`` (default): start from a valid spherical triangulation of the mesh
(:func:`sphere_nlp.starts.starting_positions`: the conformal map, repaired if needed, else the
convex embedding),
whose angles satisfy every constraint; the inequalities (3)-(5) hold by construction in that
formulation, and the three redundant vertex constraints are left out (see
:class:`sphere_nlp.nlp.AngleNLP`). Stages:

1. Area modes only (area weight > 0): :func:`area_continuation` walks the excesses from the start's
   to the targets with a log-area objective, so that the next stage starts near its optimum.
2. "margin": IPOPT on the objective (9) and the equalities with every u = alpha - e/2 kept >= a
   margin (corners already below it at the start: >= their own size less 10%, see
   :func:`margin_restart`), inside a trust region on the log excesses (a window of
   +-``angle_mode_excess_window``, area modes +-``excess_window``, around the start); re-centred,
   warm-started and with a window twice as wide each time its result touches the window. The
   paper adds its inequalities only when the equality solution breaks them, but here they cost
   little (in log u they are simple bounds, mostly far from active) and the optimum is often at a
   degenerate triangle, which an equality stage chases towards log u = -inf (see
   docs/tuning.md, "angle_mode_excess_window", for the iterations this saves).

The tuning constants are the fields of :class:`sphere_nlp.settings.SolverSettings`.
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

from .nlp import DEFAULT_FORMULATION, AngleNLP
from .settings import DEFAULT_SETTINGS
from .starts import initial_point

# What a margin stage stopped by the caller's limits yields (solve_angles's on_limit).
ON_LIMIT = ("fail", "project")
# IPOPT statuses of a run stopped short by the caller's limits (max_iter, max_time).
LIMIT_STATUSES = ("Maximum_Iterations_Exceeded", "Maximum_WallTime_Exceeded", "Maximum_CpuTime_Exceeded")


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


def solve_angles(connectivity, targets, formulation=DEFAULT_FORMULATION, ipopt_options=None,
                 max_iter=None, max_time=None, progress=None, vertices=None, start=None, on_limit="fail",
                 settings=None):
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
        Wall-clock limit in seconds per stage.
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
        :func:`sphere_nlp.starts.starting_positions`), or the paper's linear least-squares start. Default "auto"
        for log-chord, "linear" for the paper's forms. An array is a certified spherical
        triangulation of the mesh to start from (unit vectors, ``connectivity``'s numbering), for
        instance a coarser mesh's solution carried over (:mod:`sphere_nlp.hierarchy`).

    settings : SolverSettings, optional
        The tuning constants (default :class:`~sphere_nlp.settings.SolverSettings` ()).

    Returns
    -------
    AngleSolution
    """
    settings = DEFAULT_SETTINGS if settings is None else settings
    if on_limit not in ON_LIMIT:
        raise ValueError("on_limit must be one of %s, not %r" % (ON_LIMIT, on_limit))
    options = dict(settings.ipopt_options)
    if targets.area_weight > 0 and formulation == "log-chord":
        options.update(settings.area_mode_ipopt_options)
    if max_iter is not None:
        options["max_iter"] = int(max_iter)
    if max_time is not None:
        options["max_wall_time"] = float(max_time)
    options.update(ipopt_options or {})
    # Warm-started runs: small barrier and bound pushes, but the caller's options still win.
    warm_options = dict(options, **settings.warm_start_options)
    warm_options.update(ipopt_options or {})

    def stage_progress(name):
        if progress is None:
            return None
        return lambda it, f, viol, elapsed: progress(name, it, f, viol, elapsed)

    stages = []
    if start is None:
        start = "auto" if formulation == "log-chord" else "linear"
    gauge = settings.start_gauge if targets.area_weight == 0 else "area"
    initial = initial_point(connectivity, targets, start, vertices, gauge)
    init_angles, init_excess, start_kind = initial.angles, initial.excess, initial.kind
    if formulation == "log-chord":
        dropped = independent_vertices(initial.positions) if initial.positions is not None else []
        # Corners obtuse at the start get the well-conditioned form of (8) near pi (AngleNLP).
        obtuse = init_angles > settings.obtuse_angle
        # The area modes hand IPOPT the clipped Hessian (see SolverSettings.area_mode_hessian); the angle modes the exact one.
        hessian = settings.area_mode_hessian if targets.area_weight > 0 else "exact"

        def log_chord_nlp(targets, obtuse_corners, dropped_vertices=dropped, **keywords):
            return AngleNLP(connectivity, targets, formulation, dropped_vertices=dropped_vertices,
                            obtuse_corners=obtuse_corners, hessian=hessian, angle_margin=settings.angle_margin,
                            **dict(dict(dropped_penalty=settings.dropped_penalty), **keywords))

        nlp = log_chord_nlp(targets, obtuse)
        t = connectivity.n_faces
        x0 = nlp.pack(init_angles, init_excess)

        def obtuse_at(x):
            return nlp.unpack(x)[0] > settings.obtuse_angle

        mode_window = settings.excess_window if targets.area_weight > 0 else settings.angle_mode_excess_window

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
            for round_ in range(settings.max_window_rounds):
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
                                abort_violation=settings.abort_violation,
                                abort_iterations=settings.abort_iterations,
                                **warm)
                stages.append(_stage_record(name if round_ == 0 else "%s-recentred" % name, run))
                moved = np.max(np.abs(run["x"][3 * t:] - log_e), initial=0.0)
                run["touched"] = bool(moved >= 0.99 * window)
                if not run["success"] or not np.isfinite(run["x"]).all() or not run["touched"] or not recentre:
                    return run
                x, previous = run["x"], run
                window *= settings.window_growth
            return run

        x_start = x0
        if targets.area_weight > 0:
            # Each step, and the stages after the walk, flag the corners obtuse at their own start:
            # the areas reshape the triangles.
            x_start = area_continuation(nlp_for=lambda tg, x: log_chord_nlp(tg, obtuse_at(x), area_form="log"),
                                        targets=targets, x0=x0, n_faces=t, options=options,
                                        progress=stage_progress("area-continuation"), stages=stages,
                                        settings=settings)
            obtuse = obtuse_at(x_start)
            nlp = log_chord_nlp(targets, obtuse)
        # Straight to the margin stage: the optimum is often at a degenerate triangle (area modes
        # nearly always), which an equality stage chases towards log u = -inf before the margin
        # stage starts again anyway (armadillo_remeshed.obj equal-areas: 667 equality + 627 margin
        # iterations, now 638; knight.off original-areas 1,443 iterations in all, now 188;
        # nefertiti.obj original-angles 21 + 14, now 24; see docs/tuning.md).
        first_options = None
        if targets.area_weight == 0:
            first_options = dict(options, **settings.angle_mode_margin_options)
            first_options.update(ipopt_options or {})
        restart, log_u_lower, _ = margin_restart(x_start, x_start, t, nlp.angle_margin,
                                                 settings.max_margin_lift)
        direct = windowed_solve(restart, "margin", inequalities=True, log_u_lower=log_u_lower,
                                first_options=first_options)
        if on_limit == "project" and direct["status"] in LIMIT_STATUSES and np.isfinite(direct["x"]).all():
            # Stopped by the caller's limits: hand back its iterate made feasible, if that works.
            projection = project_onto_constraints(connectivity, targets, nlp, direct["x"], formulation,
                                                  dropped, options, log_u_lower, mode_window,
                                                  progress=stage_progress("projection"), settings=settings)
            stages.append(_stage_record("projection", projection))
            projected = _finish(connectivity, targets, *nlp.unpack(projection["x"]), projection, stages,
                                init_angles, init_excess, start_kind, stopped_status=direct["status"],
                                settings=settings)
            if projected.success:
                return projected
        run, with_margin = direct, True
        if _diverged(connectivity, nlp, direct["x"], settings):
            # The direct margin stage ran away from the solution set (hand_closed.obj
            # original-areas: violation 5.5): the equality stage first.
            # It gets one window: a run that ends on it is continued by the margin stage instead
            # of being re-centred, because the triangles that pull it are often degenerating
            # slivers (max_planck.obj: 4 re-centred equality runs, 534 iterations, chased two
            # corners of 0.12-1 deg slivers down to 1e-7 rad and ended in Restoration_Failed; the
            # margin stage then needed 433 more; now 38 + 64 in all).
            run = windowed_solve(x_start, "equality", recentre=False)
            with_margin, log_u_lower = False, None
            equality_diverged = _diverged(connectivity, nlp, run["x"], settings)
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
                                                                     settings.max_margin_lift,
                                                                     any_lift=True)
                # From the equality result, warm-started with its multipliers (same equalities):
                # a cold start's bound push broke (8) by 0.02-0.5 there (nefertiti.obj), and the
                # barrier then had to shrink again (knight 22 -> 18 margin iterations, spot
                # equal-angles 14 -> 9, brain equal-angles 10 -> 6, same optima).
                run = windowed_solve(restart, "margin", inequalities=True, log_u_lower=log_u_lower,
                                     warm_from=run if from_equality else None)
                with_margin = True
        penalty = settings.dropped_penalty
        violation = max_constraint_violation(connectivity, *nlp.unpack(run["x"]))
        while (violation > settings.feasibility_tolerance and np.isfinite(run["x"]).all()
               and penalty < settings.max_dropped_penalty):
            # The three left-out vertex sums come back by themselves only near the solution set
            # (the redundancy is infinitesimal); with a weak penalty the solver can stop at a metric
            # whose sums are off there (hand_closed.obj equal-angles: by 2.5e-3). A stiffer penalty,
            # from that point, pulls them back (hand: 1e6 gave 1e-13, 47 s in all, where the
            # all-constraints solve below had not finished in 15 minutes).
            penalty *= 100
            nlp = log_chord_nlp(targets, obtuse, dropped_penalty=penalty)
            run = windowed_solve(run["x"], "penalty-%.0e" % penalty, inequalities=with_margin,
                                 log_u_lower=log_u_lower)
            violation = max_constraint_violation(connectivity, *nlp.unpack(run["x"]))
        if violation > settings.feasibility_tolerance:
            # Last resort: every constraint (a singular Jacobian at the solution, so slow).
            nlp = log_chord_nlp(targets, obtuse, dropped_vertices=())
            run = windowed_solve(x_start, "all-constraints")
        angles, excess = nlp.unpack(run["x"])
        return _finish(connectivity, targets, angles, excess, run, stages, init_angles, init_excess, start_kind,
                       settings=settings)

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
    return _finish(connectivity, targets, angles, excess, run, stages, init_angles, init_excess, start_kind,
                       settings=settings)


def _diverged(connectivity, nlp, x, settings=DEFAULT_SETTINGS):
    """Whether a run ended far from the solution set (not merely short of the tolerance)."""
    if not np.isfinite(x).all():
        return True
    return max_constraint_violation(connectivity, *nlp.unpack(x)) > settings.diverged_violation


def margin_restart(x_equality, x_start, n_faces, angle_margin, max_lift=DEFAULT_SETTINGS.max_margin_lift,
                   any_lift=False):
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
    """
    margin = np.log(angle_margin)
    restart = x_start
    # A corner already below the margin at the start counts from its own size there: nefertiti.obj
    # has two of 6e-7 rad, which grew to 7e-6 in the equality stage; measured from the margin they
    # sent the margin stage back to the start (14 iterations to regain the equality objective).
    floor = np.minimum(margin, x_start[:3 * n_faces])
    from_equality = bool(np.isfinite(x_equality).all()
                         and (any_lift or np.all(x_equality[:3 * n_faces] > floor - max_lift)))
    restart = np.array(x_equality if from_equality else x_start, float)
    log_u = restart[:3 * n_faces]
    log_u_lower = np.where(log_u < margin - max_lift, log_u - 0.1, margin)
    restart[:3 * n_faces] = np.maximum(log_u, log_u_lower + 1e-3)
    return restart, log_u_lower, from_equality


def area_continuation(nlp_for, targets, x0, n_faces, options, progress=None, stages=None,
                      settings=DEFAULT_SETTINGS):
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
    n_steps = max(1, int(np.ceil(np.max(np.abs(target_log - start_log)) / settings.area_continuation_step)))
    # Only a start is needed, so each step is capped (the last iterations of a step refine the
    # weak angle term and are repeated by the next step anyway).
    capped = dict(options, max_iter=min(int(options.get("max_iter", 3000)),
                                        settings.area_continuation_iterations))
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
        if settings.area_continuation_floor:
            floor = dict(inequalities=True, log_u_lower=continuation_floor(x0, n_faces, nlp.angle_margin))
            step_options = dict(capped, **settings.area_continuation_options)
        name = "area-continuation-%s" % tau
        run = nlp.solve(x, options=step_options, progress=progress, **floor)
        if stages is not None:
            stages.append(_stage_record(name, run))
        ended = violation(nlp, run)
        for attempt in range(1, settings.area_continuation_extra_runs + 1):
            if not settings.area_continuation_violation < ended < np.inf:
                break
            rerun = nlp.solve(run["x"], options=step_options, progress=progress, **floor)
            if stages is not None:
                stages.append(_stage_record("%s-more%d" % (name, attempt), rerun))
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
        x, reached = run["x"], tau
    return x


def continuation_floor(x0, n_faces, angle_margin):
    """Lower bounds on log u for the area continuation's steps (see ``SolverSettings.area_continuation_floor``).

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
                             excess_window, progress=None, settings=DEFAULT_SETTINGS):
    """The feasible point nearest a log-chord iterate ``x`` (a stage stopped short), by IPOPT.

    The same constraints and bounds (log u >= ``log_u_lower``, log e within ``excess_window`` of
    ``x``), with the objective (9) replaced by its value's distance from the iterate: targets
    (beta, e') = the iterate's angles and excesses, both weights 1. That objective is convex in
    (alpha, e) and the start is its unconstrained minimum, so IPOPT converges like an angle mode
    from a near start (docs/tuning.md, "projection_iterations"). Run with the angle modes' small
    initial barrier and at most ``settings.projection_iterations`` iterations.

    Returns
    -------
    dict
        :meth:`sphere_nlp.nlp.AngleNLP.solve`'s result.
    """
    angles, excess = nlp.unpack(x)
    here = replace(targets, angles=angles, excess=excess, angle_weight=1.0, area_weight=1.0)
    projection = AngleNLP(connectivity, here, formulation, dropped_vertices=dropped,
                          obtuse_corners=angles > settings.obtuse_angle, angle_margin=settings.angle_margin,
                          dropped_penalty=settings.dropped_penalty)
    projection_options = dict(options, **settings.angle_mode_margin_options)
    projection_options["max_iter"] = settings.projection_iterations
    t = len(excess)
    log_e = x[3 * t:]
    return projection.solve(x, inequalities=True, options=projection_options, progress=progress,
                            excess_bounds=(log_e - excess_window, log_e + excess_window),
                            log_u_lower=log_u_lower)


def _stage_record(name, run):
    """The statistics of one IPOPT run kept in the result."""
    return dict(name=name, **{k: run[k] for k in ("status", "iterations", "objective", "time_s", "build_s")})


def _finish(connectivity, targets, angles, excess, run, stages, init_angles, init_excess, start_kind,
            stopped_status=None, settings=DEFAULT_SETTINGS):
    """The AngleSolution of the last run; ``stopped_status``: the run is the projection of a stage
    that IPOPT stopped with that status (see :func:`project_onto_constraints`)."""
    violation = max_constraint_violation(connectivity, angles, excess)
    success = bool(run["success"] and not violates_inequalities(angles, excess)
                   and violation <= settings.feasibility_tolerance)
    return AngleSolution(angles=angles, excess=excess, success=success,
                         status=stopped_status or run["status"], converged=success and stopped_status is None,
                         iterations=sum(s["iterations"] for s in stages),
                         objective=objective_value(targets, angles, excess),
                         max_constraint_violation=violation, stages=stages,
                         initial_angles=init_angles, initial_excess=init_excess, start=start_kind)
