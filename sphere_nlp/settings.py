"""The solver's tuning constants, in one frozen object.

:class:`SolverSettings` holds every constant the staged log-chord solve uses
(:func:`sphere_nlp.solve.solve_angles`), so that a caller or a test varies them by value instead of
patching module globals:

>>> from sphere_nlp.settings import SolverSettings
>>> settings = SolverSettings(area_continuation_iterations=10)
>>> settings.area_continuation_iterations, SolverSettings().area_continuation_iterations
(10, 30)
>>> settings.replace(excess_window=2.5).excess_window
2.5

Each field says what it does in a line or two; the measurements that chose its value are in
docs/tuning.md, under the field's name.
"""

import dataclasses
from dataclasses import dataclass, field
from types import MappingProxyType

import numpy as np

# IPOPT options of every run (see docs/tuning.md, "ipopt_options", for each choice).
DEFAULT_IPOPT_OPTIONS = MappingProxyType({
    "tol": 1e-8,
    # The unfolding needs the edge lengths to agree: IPOPT's default (1e-4) is far too loose.
    "constr_viol_tol": 1e-10,
    "max_iter": 3000,
    "print_level": 0,
    "sb": "yes",
    # Bounds kept exact: with IPOPT's relaxation an angle bounded by 0 can end slightly negative.
    "bound_relax_factor": 0.0,
    # AMD ordering for MUMPS: its automatic choice, and AMF, fill in badly on these KKT systems.
    "mumps_pivot_order": 0,
    # No MC64 matching and no scaling in MUMPS: the analysis otherwise used the first matrix's values.
    "mumps_permuting_scaling": 0,
    "mumps_scaling": 0,
    # MUMPS's solves are accurate enough: refine a search direction only when its residual asks.
    "min_refinement_steps": 0,
    # The filter's cap on the constraint violation (1-norm), theta_max_fact * max(1, start's):
    # IPOPT's 1e4 let one step leave the solution set for good.
    "theta_max_fact": 10.0,
    # MUMPS reserves its estimated workspace plus this percentage (IPOPT's default 1000: 11 times
    # the estimate, 34 GB at 692k vertices, which Linux refuses outright on a 24 GB machine: the
    # first factorization failed and the solve with it). Short of it, IPOPT doubles it and refactors.
    "mumps_mem_percent": 100,
})

# The area modes measure the filter's cap in the max-norm and set it to the start's violation (or
# 1): summed over 10^4-10^5 constraints, the 1-norm let single vertex sums go off by pi.
AREA_MODE_IPOPT_OPTIONS = MappingProxyType({
    "constraint_violation_norm_type": "max-norm",
    "theta_max_fact": 1.0,
})

# The angle modes' first margin run starts at a feasible point with a small barrier parameter: its
# bounds are far from most corners, and IPOPT's mu_init 0.1 first pushed into the interior and back.
ANGLE_MODE_MARGIN_OPTIONS = MappingProxyType({"mu_init": 1e-6})

# ... unless a large share of the start lies below the area floor (floor_crowd_share): thin limbs,
# whose corners' floors bind one after another under a small barrier, each step cut short where one
# more corner reaches its floor. IPOPT's adaptive barrier (Nocedal, Waechter & Waltz 2009) raises mu
# again while the iterate hugs its bounds, instead of only lowering it; its probing oracle
# (Mehrotra's predictor) costs one extra backsolve an iteration.
FLOOR_CROWD_MARGIN_OPTIONS = MappingProxyType({"mu_init": 1e-4, "mu_strategy": "adaptive", "mu_oracle": "probing"})

# A warm-started run (re-centred window, inequality stage from the equality solution): a small
# barrier and small bound pushes, so that IPOPT stays near the point it starts from.
WARM_START_OPTIONS = MappingProxyType({
    "warm_start_init_point": "yes",
    "mu_init": 1e-6,
    "warm_start_bound_push": 1e-9,
    "warm_start_bound_frac": 1e-9,
    "warm_start_slack_bound_push": 1e-9,
    "warm_start_slack_bound_frac": 1e-9,
    "warm_start_mult_bound_push": 1e-9,
})

# The area continuation's steps start the barrier small, so that the floor moves other corners little.
AREA_CONTINUATION_OPTIONS = MappingProxyType({"mu_init": 1e-4})

# An area-mode solve that starts near its targets (``area_walk_distance``) starts its margin stage
# with a small barrier: IPOPT's mu_init 0.1 first pushed the start's corners into the interior.
NEAR_START_OPTIONS = MappingProxyType({"mu_init": 1e-4})


def _frozen(mapping):
    return field(default_factory=lambda: mapping)


@dataclass(frozen=True)
class SolverSettings:
    """Tuning constants of the staged log-chord solve (see :mod:`sphere_nlp.solve`).

    Frozen: make a variant with ``SolverSettings(name=value, ...)`` or :meth:`replace`. The
    IPOPT option mappings are read-only copies of what is given (e.g. a dict). docs/tuning.md
    gives the measurements behind each default.

    Attributes
    ----------
    ipopt_options : mapping
        IPOPT options of every run; the caller's ``ipopt_options`` override them.
    area_mode_ipopt_options : mapping
        Added in the area modes: the filter's violation cap in the max-norm, at the start's.
    angle_mode_margin_options : mapping
        Added to the angle modes' first margin run and to the projection (a small initial barrier).
    floor_crowd_margin_options, floor_crowd_share : mapping, float
        Added to the angle modes' first margin run instead, when at least ``floor_crowd_share`` of
        the start's triangles lie below the area floor (thin limbs: their corners' floors bind one
        after another under a small monotone barrier): a small first barrier, adaptive (docs/tuning.md,
        "angle_mode_margin_options" and "floor_crowd_margin_options").
    unplaceable_corner_share : float
        Angle modes, named log-chord start: where the start is floor-crowded (above) and at least
        this share of its corners lie below their floors, its limbs or tail shrink past what double
        precision holds and the angle optimum under the floors is out of IPOPT's reach (thousands
        of bounds binding one at a time; docs/tuning.md, "unplaceable_corner_share"): the run maps
        the surface with the authalic route of the matching area mode instead, and says so. 0
        turns the rule off.
    multiplier_estimate_max_vertices : int
        From this many vertices IPOPT starts the constraint multipliers at 0 instead of its
        least-squares estimate (``constr_mult_init_max`` 0): the estimate costs one factorisation of
        the KKT matrix and at these sizes comes out above IPOPT's cap of 1000 and is discarded
        (docs/tuning.md).
    warm_start_options : mapping
        Added to a run warm-started from an earlier one's multipliers.
    excess_window : float
        Area modes: each run keeps every log e within this of where it started (a trust region
        against the flat direction of scaling tiny triangles together).
    angle_mode_excess_window : float
        The same for the angle modes, which start in the margin stage at a feasible point.
    max_window_rounds : int
        Runs of one stage at most: a run that ends on its window is re-centred there and repeated.
    window_growth : float
        Each re-centred run's window is this factor wider, and warm-started.
    angle_margin : float
        The margin stage keeps every u = alpha - e/2 at least this (radians); on some meshes the
        objective's infimum is at a degenerate triangle.
    corner_floor : float
        Angle modes: every corner keeps u = alpha - e/2 >= this fraction of its target angle beta
        (and >= ``angle_margin``), a plain bound in the log formulation; 0 leaves the margin alone.
    small_corner_floor, small_corner_angle : float
        Angle modes: a corner whose target is below ``small_corner_angle`` (radians) keeps at
        least ``small_corner_floor`` x its target (or the corner floor, if larger): a thin
        triangle's shape, and so its quasi-conformal distortion, turns on the relative change of
        its small corners (docs/tuning.md). A ``corner_floor`` of 0 given to
        :func:`sphere_nlp.parameterize` (``--corner-floor 0``) turns this floor off as well.
    area_mode_small_corner_floor, area_mode_sliver_angle : float
        The same in the area modes (0: off, the default; docs/tuning.md has what 0.5 does there),
        for corners whose target is at least ``area_mode_sliver_angle`` (radians): reaching its
        target area moves the apex of an input sliver across its base, and held at half their
        size, nefertiti.obj's thousands of 0.06-degree corners kept its solve from converging.
    corner_floor_pass : {"start", "needed"}
        When the corner floors become bounds: from the start ("start"), or only if the solve
        without them ends with a corner below its floor, in a second pass from the start
        ("needed"; faster on some meshes, much slower on others: docs/tuning.md).
    area_mode_corner_floor : float
        The same in the area modes.
    area_floor : float
        Every triangle keeps its excess >= this fraction of the mean 4 pi / t, so that double
        precision can place it (a bound on log e; at 1e-12 its edges are >= 1e-6 of the mean edge,
        leaving about 10 significant digits of the unit-sphere positions for its shape); 0 disables it.
    sliver_band : float
        Angle modes: a triangle whose target has a corner below 1 degree and two small corners
        a, b (radians) with ``sliver_band`` x (a + b) <= 0.5 keeps each of them within that
        relative distance of its target (bounds on log u); 0 turns it off, as does a
        ``corner_floor`` of 0. Such a sliver's apex moves along its base by
        (change of b - change of a) / (a + b) of its height, so small relative errors of its
        corners shear it a long way: the band keeps that shear below 2 x ``sliver_band``
        (docs/tuning.md, "sliver_band").
    max_floor_lift : float
        A triangle whose start is below the area floor by less than this in log e is lifted to it
        (a start off the solution set), one further below keeps its own size as bound, less
        ``below_floor_slack``. The default (0) lifts none: the start is a certified spherical
        triangulation, so its triangles are representable at their own size, and lifting a limb's
        tip by orders of magnitude puts the start far off the solution set (a limbed body of 27k
        vertices: over 570 iterations and 900 s against 27; docs/tuning.md). An area floor given
        explicitly (``area_floor=``, ``--area-floor``, and the recovery's) lifts every one (inf),
        so that it holds at the end.
    below_floor_slack : float
        How far in log e a triangle that keeps its own size as bound (not lifted) may still shrink:
        its bound is its start's e x exp(-below_floor_slack). At 1 the bound does not bind where the
        conformal start's tips are near the optimum's (a limbed body of 50k vertices: 23 iterations,
        against 42 with 0.1; docs/tuning.md).
    max_margin_lift : float
        The margin stage lifts corners below the margin to it only if that changes none of them by
        more than this in log u (else it starts from its own start; see
        :func:`sphere_nlp.solve.margin_restart`).
    dropped_penalty : float
        Weight of the penalty on the three left-out vertex sums (see :class:`sphere_nlp.nlp.LogChordNLP`).
    max_dropped_penalty : float
        If those sums have not come back, the penalty is raised 100-fold at a time up to this.
    max_sum_drift : float
        At a vertex whose sum (7), left out and held by that penalty alone, would drift from 2 pi by
        more than this (radians, a linear estimate of the angle term's pull towards its targets'
        sum: :func:`sphere_nlp.solve.dropped_sum_drift`; about 6 at a spike's tip), the solver's
        corner targets are shifted to sum to 2 pi, an equivalent objective
        (:func:`sphere_nlp.solve.summed_targets`); inf: never.
    feasibility_tolerance : float
        A solve counts only if every equality (6)-(8) holds to this, whatever IPOPT reports.
    diverged_violation : float
        A run that ends with a larger max violation has left the solution set; runs that merely stop
        short end far below it.
    abort_violation, abort_iterations : float, int
        A log-chord run is stopped as "Diverged" once its violation has stayed above
        ``abort_violation`` for ``abort_iterations`` iterations in a row.
    sound_violation, diverged_resumes : float, int
        A diverged margin stage resumes (at most ``diverged_resumes`` times) from its iterate of
        least objective among those whose max violation was at most ``sound_violation``
        (:func:`sphere_nlp.solve.resume_diverged`).
    area_continuation_step : float
        Area modes: each continuation step moves every log excess by at most this.
    area_continuation_iterations : int
        ... with at most this many IPOPT iterations (the steps only make a start).
    area_continuation_violation : float
        A step that ends further than this from the solution set (max |residual|) is run again
        from where it ended ...
    area_continuation_extra_runs : int
        ... up to this many times;
    area_continuation_halvings : int
        and if a re-run gets no nearer, the step is halved from the last point reached, up to this
        many times in the whole walk.
    area_continuation_floor : bool
        The steps keep every corner u above the margin (a corner already below it: above its own
        start size less 10%), so that they do not collapse corners towards u = 0.
    area_continuation_options : mapping
        Added to the steps' IPOPT options when the floor is on (a small initial barrier).
    area_continuation_weighting : {"uniform", "objective"}
        How the steps weigh each triangle's log-area error (log e - log e'_tau)^2: all alike
        ("uniform"), or by (e' / e_mean)^2 of its final target e', so that near the targets the
        steps' area term is (9)'s to second order and the walk ends near (9)'s optimum
        ("objective": lower objectives on 8 of 11 original-areas rows and fewer iterations up to
        15k vertices, but more at 43k-50k; docs/tuning.md). The same in equal-areas, whose targets
        are equal.
    area_walk_distance : float
        Area modes: the walk is skipped when the start's excesses are already within this of the
        targets, as the mean |log(e / e')| over the triangles: a start that is itself a map near the
        area targets (an earlier result, the map of a mesh of the same connectivity and similar
        shape), which the walk's log-area steps would move away from (0 always walks). The
        conformal start is at 2-7 on the shared meshes, area-mode optima at 0.02-0.05.
    near_start_options : mapping
        Added to the first margin run's IPOPT options when the walk is skipped (a small barrier).
    area_mode_hessian, angle_mode_hessian : {"exact", "clipped", "clipped-corners"}
        The Hessian the area and the angle modes hand IPOPT (:class:`sphere_nlp.nlp.LogChordNLP`'s
        ``hessian``; docs/tuning.md).
    semidefinite_block_share : float
        Log-chord: the Lagrangian Hessian's 4x4 block of every triangle whose excess is below this
        fraction of its share of the sphere (4 pi / t) is handed to IPOPT with its negative
        eigenvalues set to 0 (:class:`sphere_nlp.nlp.LogChordNLP`'s ``semidefinite_below_excess``;
        0 never): a thin limb's tips, below what positions hold, make the Hessian indefinite and
        IPOPT's inertia correction then damps every step (docs/tuning.md).
    projection_iterations : int
        Iteration cap of the projection of a stage stopped by the caller's limits (``max_iter``
        does not apply to it; ``max_time`` does).
    min_stage_iterations, stage_iterations_per_vertex : int, float
        Log-chord, when the caller gives no ``max_iter``: every IPOPT run stops after
        max(``min_stage_iterations``, ``stage_iterations_per_vertex`` x n) iterations for n
        vertices (at most ``ipopt_options``' max_iter, reached at 30k vertices); a margin stage
        stopped there is projected onto the constraints as with ``on_limit="project"`` (a certified
        map, not optimal, ``converged`` False), so that a small mesh never runs thousands of
        iterations (:func:`sphere_nlp.solve.stage_iteration_cap`; docs/tuning.md).
    obtuse_angle : float
        Corners above this angle where a stage starts use the obtuse form of (8) (LogChordNLP).
    start_gauge : {"excess", "area"}
        Mobius normalisation of the angle modes' start (:func:`sphere_nlp.starts.starting_positions`);
        the area modes keep "area" (their continuation sets the scale).
    authalic_steps, authalic_work, polish_iterations, polish_work, min_polish_iterations : int
    authalic_tolerance : float
        Area modes: the run's default budget (:func:`sphere_nlp.polish.default_budget`), counted in
        work so that the same input gives the same map on any machine at any load: at most
        ``authalic_work / n`` steps of the authalic descent (at least ``authalic_steps``, at most
        ten times as many; it stops earlier once its mean |log area ratio| is below
        ``authalic_tolerance``, a sixth of the 0.03 the modes aim for), then ``polish_work / n`` IPOPT
        iterations of the NLP's polish in each of its runs for n vertices, at most
        ``polish_iterations``, none below ``min_polish_iterations`` (its iterate is then projected
        onto the constraints). ``max_time`` replaces it by a wall-clock limit.
    authalic_extension : float
        Area modes, default budget: a descent whose steps end above the 0.03 the modes aim for
        goes on while above it, for at most this many times its steps more (still counted in
        steps, so still the same map at any load; docs/tuning.md).
    authalic_share : float
        With ``max_time``: the fraction of the time left that the authalic stage may take; the
        polish has the rest.
    authalic_stall : float
        The authalic stage also stops when its energy fell by less than this fraction over its
        last 50 steps.
    polish_slack : float
        The polish keeps each triangle's |log(e / e')| within this of the authalic map's, so that
        a triangle already at its target keeps some room (:func:`sphere_nlp.polish.no_worse_band`).
    on_run : callable(stage, nlp, run), optional
        Called after every IPOPT run with the run's name (e.g. "margin", "margin-recentred",
        "area-continuation-1/2"), its NLP (:func:`sphere_nlp.nlp.AngleNLP`) and its
        :class:`sphere_nlp.nlp.IpoptRun` (start, end point, multipliers, status): for traces and
        benchmarks to observe the solve. It may return an IpoptRun to use instead (for
        experiments and tests, e.g. to inject a failure); None keeps the run. Not a tuning
        constant; the default None does nothing.
    on_iterate : callable(stage, iteration, x, lam_g, lam_x, objective), optional
        Called with every IPOPT iterate of every run (copies), for traces and checkpoints.
    modify_hessian : callable(stage, evaluator, x, lam_f, lam_g, values) -> values, optional
        For experiments only: replaces the Lagrangian Hessian handed to IPOPT at every evaluation
        of every run (see :meth:`sphere_nlp.nlp.LogChordNLP.solve`'s ``modify_hessian``); the
        result is then no longer the solver's.
    """

    ipopt_options: MappingProxyType = _frozen(DEFAULT_IPOPT_OPTIONS)
    area_mode_ipopt_options: MappingProxyType = _frozen(AREA_MODE_IPOPT_OPTIONS)
    angle_mode_margin_options: MappingProxyType = _frozen(ANGLE_MODE_MARGIN_OPTIONS)
    floor_crowd_margin_options: MappingProxyType = _frozen(FLOOR_CROWD_MARGIN_OPTIONS)
    floor_crowd_share: float = 0.2
    unplaceable_corner_share: float = 0.015
    multiplier_estimate_max_vertices: int = 100_000
    warm_start_options: MappingProxyType = _frozen(WARM_START_OPTIONS)
    excess_window: float = 5.0
    angle_mode_excess_window: float = 20.0
    max_window_rounds: int = 6
    window_growth: float = 2.0
    angle_margin: float = 1e-4
    corner_floor: float = 0.1
    small_corner_floor: float = 0.5
    small_corner_angle: float = np.radians(10.0)
    area_mode_small_corner_floor: float = 0.0
    area_mode_sliver_angle: float = np.radians(1.0)
    corner_floor_pass: str = "start"
    area_mode_corner_floor: float = 0.0
    area_floor: float = 1e-12
    sliver_band: float = 2.5
    max_floor_lift: float = 0.0
    below_floor_slack: float = 1.0
    max_margin_lift: float = 1.0
    dropped_penalty: float = 100.0
    max_dropped_penalty: float = 1e6
    max_sum_drift: float = 1.0
    feasibility_tolerance: float = 1e-8
    diverged_violation: float = 0.1
    abort_violation: float = 1.0
    abort_iterations: int = 50
    sound_violation: float = 1e-2
    diverged_resumes: int = 2
    area_continuation_step: float = 6.0
    area_continuation_iterations: int = 30
    area_continuation_violation: float = 0.2
    area_continuation_extra_runs: int = 3
    area_continuation_halvings: int = 3
    area_continuation_floor: bool = True
    area_continuation_options: MappingProxyType = _frozen(AREA_CONTINUATION_OPTIONS)
    area_continuation_weighting: str = "uniform"
    area_walk_distance: float = 0.1
    near_start_options: MappingProxyType = _frozen(NEAR_START_OPTIONS)
    area_mode_hessian: str = "clipped"
    angle_mode_hessian: str = "clipped-corners"
    semidefinite_block_share: float = 1e-16
    projection_iterations: int = 50
    min_stage_iterations: int = 300
    stage_iterations_per_vertex: float = 0.1
    obtuse_angle: float = np.pi / 2
    start_gauge: str = "excess"
    authalic_steps: int = 300
    authalic_work: int = 1_500_000
    authalic_tolerance: float = 5e-3
    authalic_extension: float = 3.0
    polish_iterations: int = 30
    polish_work: int = 60_000
    min_polish_iterations: int = 10
    authalic_share: float = 0.75
    authalic_stall: float = 1e-3
    polish_slack: float = 0.0
    on_run: object = None
    on_iterate: object = None
    modify_hessian: object = None

    def __post_init__(self):
        # A plain dict given for an option mapping is copied read-only, so the object stays frozen.
        for name in ("ipopt_options", "area_mode_ipopt_options", "angle_mode_margin_options", "floor_crowd_margin_options",
                     "warm_start_options", "area_continuation_options", "near_start_options"):
            object.__setattr__(self, name, MappingProxyType(dict(getattr(self, name))))
        for name in ("small_corner_floor", "area_mode_small_corner_floor"):
            if not 0.0 <= getattr(self, name) < 1.0:
                raise ValueError("%s must be in [0, 1), not %r" % (name, getattr(self, name)))
        if not self.sliver_band >= 0:
            raise ValueError("sliver_band must be >= 0, not %r" % (self.sliver_band,))
        if not self.semidefinite_block_share >= 0:
            raise ValueError("semidefinite_block_share must be >= 0, not %r" % (self.semidefinite_block_share,))
        if self.corner_floor_pass not in ("start", "needed"):
            raise ValueError("corner_floor_pass must be 'start' or 'needed', not %r" % (self.corner_floor_pass,))

    def replace(self, **changes):
        """A copy with ``changes`` applied (:func:`dataclasses.replace`)."""
        return dataclasses.replace(self, **changes)


DEFAULT_SETTINGS = SolverSettings()
