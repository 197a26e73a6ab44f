"""The staged solve (sphere_nlp.solve): area continuation, margin stage and its fall-backs, the
formulations against each other."""

import dataclasses
from fractions import Fraction

import numpy as np
import pytest

import sphere_nlp
from sphere_nlp.certify import certify
from sphere_nlp.connectivity import build_connectivity
from sphere_nlp.nlp import AngleNLP, IpoptRun, LogChordNLP
from sphere_nlp.settings import SolverSettings
from sphere_nlp import starts
from sphere_nlp.targets import MODES, make_targets

from conftest import small_log_chord_problem
from meshgen import ellipsoid, spike_sphere, tentacle_creature

SETTINGS = SolverSettings()


@pytest.mark.parametrize("mode", MODES)
def test_formulations_reach_the_same_optimum(mode):
    V, F = ellipsoid(2)
    # Area modes are nonconvex, so all formulations start from the same point (the paper's).
    results = {f: sphere_nlp.parameterize((V, F), target=mode, formulation=f, start="linear")
               for f in ("faithful", "substituted", "log-chord")}
    reference = results["faithful"].objective
    for f, r in results.items():
        assert r.certificate.valid, f
        assert abs(r.objective - reference) <= 1e-8 * max(1.0, abs(reference)), (f, r.objective, reference)
        np.testing.assert_allclose(r.angles, results["faithful"].angles, atol=1e-6)


def test_area_continuation_walks_the_log_excesses_to_the_targets():
    # The area modes' first phase: steps of at most AREA_CONTINUATION_STEP per log excess, each
    # capped, ending with the excesses close to the targets although the start is far from them.
    from sphere_nlp import solve

    V, F = ellipsoid(2, axes=(1.0, 3.0, 0.4))
    c = build_connectivity(F, len(V))
    targets = make_targets("equal-areas", V, F, c.vertex_degree)
    angles, excess, positions, _ = starts.feasible_start(c, V)
    nlp = AngleNLP(c, targets, "log-chord", dropped_vertices=solve.independent_vertices(positions),
                   area_form="log")
    x0 = nlp.pack(angles, excess)
    stages = []
    x = solve.area_continuation(
        lambda tg, x: AngleNLP(c, tg, "log-chord", dropped_vertices=solve.independent_vertices(positions),
                            area_form="log"),
        targets, x0, c.n_faces, dict(SETTINGS.ipopt_options), stages=stages)
    start_error = np.abs(np.log(excess / targets.excess))
    n_steps = int(np.ceil(start_error.max() / SETTINGS.area_continuation_step))
    assert n_steps >= 2 and len(stages) == n_steps
    assert all(s["iterations"] <= SETTINGS.area_continuation_iterations for s in stages)
    solved_angles, solved_excess = nlp.unpack(x)
    assert solve.max_constraint_violation(c, solved_angles, solved_excess) < 0.05   # measured 0.005
    error = np.abs(np.log(solved_excess / targets.excess))
    assert error.mean() < 0.1 * start_error.mean()


def _stretched_ellipsoid_start():
    """An ellipsoid far from equal areas: its connectivity, equal-area targets, and the feasible
    start's angles, excesses and left-out vertices."""
    from sphere_nlp import solve

    V, F = ellipsoid(2, axes=(1.0, 3.0, 0.4))
    c = build_connectivity(F, len(V))
    targets = make_targets("equal-areas", V, F, c.vertex_degree)
    angles, excess, positions, _ = starts.feasible_start(c, V)
    dropped = solve.independent_vertices(positions)
    return c, targets, angles, excess, dropped


def test_area_continuation_reruns_a_step_that_ends_far_from_feasible():
    # A step whose capped run ends with its equalities off by more than AREA_CONTINUATION_VIOLATION
    # is run again from there (at most AREA_CONTINUATION_EXTRA_RUNS times) once the halvings are
    # spent (none here). This ellipsoid's steps end within 4e-4 even when capped at a few
    # iterations, so the bound is lowered to 1e-6 here.
    from sphere_nlp import solve

    c, targets, angles, excess, dropped = _stretched_ellipsoid_start()

    def nlp_for(tg, x):
        return AngleNLP(c, tg, "log-chord", dropped_vertices=dropped, area_form="log")

    x0 = nlp_for(targets, None).pack(angles, excess)
    settings = SolverSettings(area_continuation_iterations=3, area_continuation_violation=1e-6,
                              area_continuation_halvings=0)
    violation, names = {}, {}
    for extra in (0, 20):
        stages = []
        x = solve.area_continuation(nlp_for, targets, x0, c.n_faces, dict(settings.ipopt_options),
                                    stages=stages, settings=settings.replace(area_continuation_extra_runs=extra))
        violation[extra] = np.max(np.abs(nlp_for(targets, None).evaluate(x)[1]))
        names[extra] = [s["name"] for s in stages]
    assert not any("-more" in n for n in names[0]) and any("-more" in n for n in names[20])
    assert violation[0] > settings.area_continuation_violation >= violation[20]


def test_area_continuation_halves_the_step_when_a_rerun_drifts_further():
    # The walk's control flow with scripted runs: a step that ends far is re-run while that brings
    # it nearer; once a re-run ends no nearer, the step is halved and tried from the last point
    # the walk reached (not from the drifted one).
    from sphere_nlp import solve

    V, F = ellipsoid(1)
    c = build_connectivity(F, len(V))
    targets = make_targets("equal-areas", V, F, c.vertex_degree)
    t = c.n_faces
    x0 = np.concatenate([np.zeros(3 * t), np.log(targets.excess) + 7.0])   # two steps of 3.5
    ends = iter([0.5, 0.3, 0.4,       # tau 1/2: far, nearer, further -> halve
                 0.01,                # tau 1/4 from x0: near
                 0.01, 0.01, 0.01])   # tau 1/2, 3/4, 1
    starts, floors = [], []

    class ScriptedNLP:
        violation_of = {}                     # run number (every entry of its x) -> its violation
        angle_margin = 1e-4

        def solve(self, x, options=None, progress=None, **bounds):
            starts.append(x)
            floors.append((bounds.get("inequalities"), bounds.get("log_u_lower"), options.get("mu_init")))
            self.violation_of[len(starts)] = next(ends)
            return IpoptRun(x0=x, x=np.full_like(x0, len(starts)), lam_g=np.zeros(0), lam_x=np.zeros(0),
                            status="Maximum_Iterations_Exceeded", iterations=30, objective=0.0)

        def evaluate(self, x):
            return 0.0, np.array([self.violation_of[int(x[0])]])

    scripted = ScriptedNLP()
    settings = SolverSettings(area_continuation_extra_runs=3, area_continuation_halvings=1)
    stages = []
    x = solve.area_continuation(lambda tg, x: scripted, targets, x0, t, {}, stages=stages, settings=settings)
    names = [s["name"] for s in stages]
    assert names == ["area-continuation-1/2", "area-continuation-1/2-more1", "area-continuation-1/2-more2",
                     "area-continuation-1/4", "area-continuation-1/2", "area-continuation-3/4",
                     "area-continuation-1"]
    assert starts[0] is x0 and starts[3] is x0           # the halved step starts where the walk was
    assert int(starts[1][0]) == 1 and int(starts[2][0]) == 2
    assert int(x[0]) == 7
    # Every run kept the corners above the margin, with a small barrier parameter.
    x0[0] = np.log(1e-6)                                 # a corner below the margin at the start
    floors.clear()
    ends = iter([0.01] * 2)
    solve.area_continuation(lambda tg, x: scripted, targets, x0, t, {}, settings=settings)
    floor = solve.continuation_floor(x0, t, 1e-4)
    assert floor[0] == np.log(1e-6) - 0.1 and np.all(floor[1:] == np.log(1e-4))
    assert all(ineq is True and np.array_equal(lower, floor) and mu == settings.area_continuation_options["mu_init"]
               for ineq, lower, mu in floors) and len(floors) == 2


def test_area_continuation_halves_a_step_that_ends_far_and_retries_from_the_last_good_point():
    # With no re-runs, a step that ends further than AREA_CONTINUATION_VIOLATION is tried again with
    # half the step from the point the walk had reached, AREA_CONTINUATION_HALVINGS times in all; the walk still
    # ends at the targets (tau = 1). Each run is recorded, so the runs' starts show where it went on from.
    from sphere_nlp import solve

    c, targets, angles, excess, dropped = _stretched_ellipsoid_start()
    runs = []

    class RecordingNLP(LogChordNLP):
        def solve(self, x0, **kw):
            run = super().solve(x0, **kw)
            runs.append((np.array(x0), run.x))
            return run

    def nlp_for(tg, x):
        return RecordingNLP(c, tg, dropped_vertices=dropped, area_form="log")

    x0 = nlp_for(targets, None).pack(angles, excess)
    settings = SolverSettings(area_continuation_iterations=3,
                              area_continuation_violation=1e-6,     # every capped step ends "far"
                              area_continuation_extra_runs=0, area_continuation_halvings=2)
    stages = []
    x = solve.area_continuation(nlp_for, targets, x0, c.n_faces, dict(settings.ipopt_options),
                                stages=stages, settings=settings)
    n_steps = int(np.ceil(np.max(np.abs(np.log(excess / targets.excess))) / settings.area_continuation_step))
    taus = [float(Fraction(s["name"].rsplit("-", 1)[1])) for s in stages]
    # 1/n far, 1/(2n) far, then steps of 1/(4n) from x0 to 1
    expected = [1 / n_steps, 1 / (2 * n_steps)] + [k / (4 * n_steps) for k in range(1, 4 * n_steps + 1)]
    np.testing.assert_allclose(taus, expected, rtol=1e-12)
    assert all(np.array_equal(start, x0) for start, _ in runs[:3])        # retried from the start
    assert all(np.array_equal(runs[k + 1][0], runs[k][1]) for k in range(2, len(runs) - 1))
    assert np.array_equal(x, runs[-1][1])
    # No step shrank a corner below the floor (the margin, or its own start size less 10%).
    floor = solve.continuation_floor(x0, c.n_faces, 1e-4)
    assert all(np.all(end[:3 * c.n_faces] >= floor) for _, end in runs)


@pytest.mark.parametrize("mode", ["equal-areas", "original-areas"])
def test_area_modes_from_a_far_start(mode):
    # The surface's conformal map of a long ellipsoid crowds its ends, far from the area targets
    # (original-areas starts there; equal-areas from its targets' metric, which does not crowd
    # them, so it is given that start here); the area modes must still end at a solution of (9)
    # itself: the last stage solves the paper's objective, started from the continuation.
    from sphere_nlp import starts

    V, F = ellipsoid(3, axes=(1.0, 4.0, 0.5))
    surface, _ = starts.starting_positions(build_connectivity(F, len(V)), V)
    r = sphere_nlp.parameterize((V, F), target=mode, start=surface)
    names = [s["name"] for s in r.stages]
    assert len(names) >= 3 and all(n.startswith("area-continuation") for n in names[:2])
    assert not names[-1].startswith("area-continuation")      # the last stage solves (9) itself
    # ... straight in the margin stage (no equality stage chasing degenerate corners), so every
    # u = alpha - e/2 keeps the margin.
    assert "equality" not in names and names[len([n for n in names if n.startswith("area")])] == "margin"
    assert (r.angles - r.excess[:, None] / 2).min() >= 1e-4 * (1 - 1e-9)
    assert r.certificate.valid and r.max_constraint_violation <= 1e-8 and r.max_angle_error <= 1e-6
    assert np.median(np.abs(np.log(r.excess / r.target_excess))) < 0.05


def test_margin_restart_never_lifts_a_corner_far():
    from sphere_nlp.solve import margin_restart
    MAX_MARGIN_LIFT = SETTINGS.max_margin_lift
    margin, t = 1e-4, 2
    log_margin = np.log(margin)
    start = np.log(np.array([0.5, 0.5, 2.0, 6e-7, 0.3, 2.8, 0.01, 0.02]))   # a start corner of 6e-7
    near = start.copy()
    near[:3] = np.log([0.5, 0.5 * margin, 2.0])                            # equality result: 0.5 margin
    near[3] = np.log(0.5)
    restart, lower, from_equality = margin_restart(near, start, t, margin)
    # Lifting 0.5 * margin to the margin is a small change: the equality result is used, lifted.
    assert from_equality and np.allclose(lower, log_margin)
    assert np.all(restart[:6] >= log_margin + 1e-3 - 1e-12)
    assert restart[1] == pytest.approx(log_margin + 1e-3) and np.array_equal(restart[6:], near[6:])
    far = near.copy()
    far[1] = log_margin - MAX_MARGIN_LIFT - 5                               # driven to 1e-8-ish
    restart, lower, from_equality = margin_restart(far, start, t, margin)
    # ... too far to lift: restart from the stage's start, whose own tiny corner keeps its size.
    assert not from_equality and np.array_equal(restart[6:], start[6:]) and restart[3] == start[3]
    assert lower[3] == pytest.approx(start[3] - 0.1) and np.allclose(np.delete(lower, 3), log_margin)
    assert np.all(restart[:6] > lower)
    kept = near.copy()
    kept[3] = start[3] + 0.5                                                # the tiny start corner, grown
    restart, lower, from_equality = margin_restart(kept, start, t, margin)
    # A corner tiny at the start does not count as driven down: the equality result is used.
    assert from_equality and np.array_equal(restart[6:], kept[6:]) and restart[3] == kept[3]
    assert lower[3] == pytest.approx(kept[3] - 0.1)
    restart, _, from_equality = margin_restart(np.full(8, np.nan), start, t, margin)  # diverged
    assert not from_equality and np.array_equal(restart[6:], start[6:])
    # With no lift limit (after a diverged direct margin stage) the equality result is kept as it
    # is: its far corner keeps its own size as bound instead of being lifted.
    restart, lower, from_equality = margin_restart(far, start, t, margin, any_lift=True)
    assert from_equality and np.array_equal(restart, far) and lower[1] == pytest.approx(far[1] - 0.1)


def test_margin_restart_lifts_a_corner_to_its_floor_however_far_above_the_margin_it_is():
    # The corner floors (0.1 beta) can be a hundred times the margin: an area mode's walk ends with
    # corners near the margin, which the floor a caller asked for must still hold at the end.
    from sphere_nlp.solve import margin_restart
    margin, t = 1e-4, 2
    start = np.log(np.array([0.5, 2e-4, 2.0, 6e-7, 0.3, 2.8, 0.01, 0.02]))
    floor = np.log(np.array([0.05, 0.05, 0.2, 0.05, 0.03, 0.28]))
    restart, lower, from_equality = margin_restart(start, start, t, margin, log_floor=floor)
    assert from_equality
    # 2e-4 is 5.5 below its floor in the log (more than max_margin_lift): lifted to it all the same.
    assert lower[1] == floor[1] and restart[1] == pytest.approx(floor[1] + 1e-3)
    # 6e-7 is far below the angle margin itself: it keeps its own size, less 10%, as bound.
    assert lower[3] == pytest.approx(start[3] - 0.1) and restart[3] == start[3]
    assert np.array_equal(np.delete(lower, 3), np.delete(floor, 3))
    assert np.all(restart[:6] > lower) and np.array_equal(restart[6:], start[6:])


def _diverging_runs(count, keep_best=False, keep_x=False):
    """An ``on_run`` hook that makes the first ``count`` "margin" or "equality" runs end at NaN
    (a diverged run, whatever IPOPT did), and the real verdicts on those runs. Unless ``keep_best``,
    the runs had no iterate near the constraints to resume from (``best_sound``). With ``keep_x``
    they end where they ended, stopped as "Diverged" by the watch on IPOPT's own violation."""
    from sphere_nlp import solve

    verdicts, starts = [], []

    def on_run(stage, nlp, run):
        if stage == "margin":
            starts.append(run.x0)
        if stage in ("margin", "equality") and len(verdicts) < count:
            verdicts.append(solve.diverged(nlp.connectivity, nlp, run.x))
            return dataclasses.replace(run, x=run.x if keep_x else np.full_like(run.x, np.nan), status="Diverged",
                                       best_sound=run.best_sound if keep_best else None)
        return None

    return SolverSettings(on_run=on_run), verdicts, starts


@pytest.mark.parametrize("mode", ["original-areas", "original-angles"])
def test_falls_back_to_the_equality_stage_when_the_direct_margin_stage_diverges(mode):
    # hand_closed.obj original-areas: the margin stage straight from the continuation ended with
    # violation 5.5; the equality-first path must then run and still certify. The angle modes
    # start in the margin stage too, with the same fall-back.
    settings, verdicts, _ = _diverging_runs(1)
    V, F = ellipsoid(2, axes=(1.0, 2.0, 0.7))
    r = sphere_nlp.parameterize((V, F), target=mode, settings=settings, start="conformal")
    names = [s["name"] for s in r.stages if not s["name"].startswith("area")]
    assert names[0] == "margin" and "equality" in names[1:]
    assert verdicts[0] is False                   # the real check passed that run: no false alarm
    assert r.certificate.valid and r.max_constraint_violation <= 1e-8


def test_the_equality_fallback_keeps_the_corner_floors_asked_for():
    # The equality stage has no bounds: its result, near the optimum without floors, collapses the
    # tentacles' corners (an area mode), so the margin stage must follow from it, lifting them.
    settings, _, _ = _diverging_runs(1)
    V, F = tentacle_creature()
    r = sphere_nlp.parameterize((V, F), target="original-areas", settings=settings, corner_floor=0.1, start="conformal")
    names = [s["name"] for s in r.stages if not s["name"].startswith("area")]
    assert names[:3] == ["margin", "equality", "margin"]
    u = r.angles - r.excess[:, None] / 2
    assert (u >= 0.1 * r.target_angles * (1 - 1e-9)).all()
    assert r.certificate.valid and r.max_constraint_violation <= 1e-8


def test_the_equality_fallback_keeps_the_area_floor():
    # The equality stage has no bounds: on this ellipsoid its result, the optimum without floors,
    # has triangles of 0.05 of the mean and every corner clear of its floor, so only the area floor
    # tells that the margin stage must follow from it.
    settings, _, _ = _diverging_runs(1)
    V, F = ellipsoid(2, axes=(1.0, 2.0, 0.7))
    r = sphere_nlp.parameterize((V, F), target="original-angles", settings=settings, area_floor=0.1)
    assert [s["name"] for s in r.stages][:3] == ["margin", "equality", "margin"]
    assert r.excess.min() >= 0.1 * 4 * np.pi / len(F) * (1 - 1e-9)
    assert r.certificate.valid and r.max_constraint_violation <= 1e-8


@pytest.mark.parametrize("mode, keep_x", [("original-areas", False), ("equal-areas", False),
                                          ("original-angles", False), ("original-areas", True)])
def test_a_diverged_margin_stage_resumes_from_its_best_iterate_near_the_constraints(mode, keep_x):
    # A margin stage that runs off after most of its way keeps its best sound iterate; the stage
    # resumes from there (warm-started) instead of starting the equality fallback from scratch, and
    # reaches the optimum of the undisturbed solve in a few iterations. A run the watch stopped
    # counts as diverged even where the cosine form of (8) is small at its end (keep_x).
    V, F = ellipsoid(2, axes=(1.0, 2.0, 0.7))
    reference = sphere_nlp.parameterize((V, F), target=mode, start="conformal")
    settings, verdicts, _ = _diverging_runs(1, keep_best=True, keep_x=keep_x)
    r = sphere_nlp.parameterize((V, F), target=mode, settings=settings, start="conformal")
    names = [s["name"] for s in r.stages if not s["name"].startswith("area")]
    assert names[:2] == ["margin", "margin-resumed"] and "equality" not in names
    resumed = [s for s in r.stages if s["name"] == "margin-resumed"]
    assert resumed[0]["iterations"] <= 10
    assert r.objective == pytest.approx(reference.objective, rel=1e-8)
    assert r.certificate.valid and r.max_constraint_violation <= 1e-8


def test_a_run_keeps_its_least_objective_iterate_within_the_sound_violation():
    # best_sound is an actual iterate of the run (the constraints at most sound_violation off),
    # with its multipliers, and none is kept by a run that does not watch for divergence.
    c, nlp, x = small_log_chord_problem()
    x = x + 0.05 * np.sin(np.arange(len(x)))          # off the constraints, so that it has a way to go
    iterates, reports = [], []
    run = nlp.solve(x, inequalities=True, abort_violation=1.0, sound_violation=1e-3,
                    progress=lambda i, f, violation, elapsed: reports.append((f, violation)),
                    on_iterate=lambda i, xi, lam_g, lam_x, f: iterates.append(xi))
    best = run.best_sound
    assert best is not None and best.iteration > 0 and np.array_equal(best.x, iterates[best.iteration])
    assert best.violation <= 1e-3 and best.lam_g.shape == run.lam_g.shape
    assert best.objective == min(f for f, violation in reports if violation <= 1e-3)
    assert reports[0][1] > 1e-3                        # the start is not among them
    assert nlp.solve(x, inequalities=True).best_sound is None


def test_after_two_diverged_runs_the_margin_stage_starts_from_the_feasible_start():
    # If the equality stage of the fall-back diverges too, neither its result nor the continuation's
    # end (the diverged direct run's start) may be the margin stage's start.
    from sphere_nlp.starts import feasible_start

    settings, _, starts = _diverging_runs(2)
    V, F = ellipsoid(2, axes=(1.0, 2.0, 0.7))
    r = sphere_nlp.parameterize((V, F), target="original-areas", settings=settings, start="conformal")
    names = [s["name"] for s in r.stages if not s["name"].startswith("area")]
    assert names[:3] == ["margin", "equality", "margin"]
    continuation_end, fallback = starts[:2]
    c = build_connectivity(F, len(V))
    angles, excess, _, _ = feasible_start(c, V, gauge="area")
    x0 = AngleNLP(c, make_targets("original-areas", V, F, c.vertex_degree)).pack(angles, excess)
    assert np.allclose(fallback, x0)
    assert not np.allclose(continuation_end, x0)
    assert r.certificate.valid and r.max_constraint_violation <= 1e-8


def test_diverged_flags_non_finite_or_far_infeasible_points_only():
    from sphere_nlp import solve

    c, nlp, x = small_log_chord_problem()
    assert not solve.diverged(c, nlp, x)
    x_off = x.copy()
    x_off[0] += 1.0                     # one corner e times larger: a vertex sum off by far more than 0.1
    assert solve.diverged(c, nlp, x_off)
    assert solve.diverged(c, nlp, np.full_like(x, np.nan))


def test_on_run_sees_every_run_and_the_settings_cannot_change_under_it():
    # The public per-run hook: one call per IPOPT run, in order, with the records the result keeps;
    # the settings object is frozen, its IPOPT options read-only.
    from sphere_nlp.nlp import status_kind

    seen = []
    settings = SolverSettings(on_run=lambda stage, nlp, run: seen.append((stage, run)))
    V, F = ellipsoid(1, axes=(1.0, 2.0, 0.7))
    r = sphere_nlp.parameterize((V, F), target="original-areas", settings=settings, start="conformal")
    assert [stage for stage, _ in seen] == [s["name"] for s in r.stages]
    assert [run.iterations for _, run in seen] == [s["iterations"] for s in r.stages]
    assert all(run.x0.shape == run.x.shape for _, run in seen)
    assert seen[-1][1].success and status_kind(r.status) == "solved" and r.certificate.valid
    assert [status_kind(s) for s in ("Maximum_WallTime_Exceeded", "Diverged", "Restoration_Failed")] == [
        "limit", "diverged", "failed"]
    with pytest.raises(dataclasses.FrozenInstanceError):
        settings.excess_window = 1.0
    with pytest.raises(TypeError):
        settings.ipopt_options["tol"] = 1.0
    given = {"tol": 1e-6}
    with pytest.raises(TypeError):
        SolverSettings(ipopt_options=given).ipopt_options["tol"] = 1.0      # a read-only copy


def test_settings_of_another_type_are_refused_before_solving():
    from sphere_nlp.errors import UsageError

    with pytest.raises(UsageError, match="settings must be a sphere_nlp.SolverSettings, not dict"):
        sphere_nlp.parameterize(ellipsoid(1), settings={"excess_window": 2.0})


def test_weighted_area_continuation_ends_near_the_objectives_optimum():
    # The walk's term weighted by (e'/e_mean)^2 is (9)'s quadratic model at the targets, so its last
    # step ends near (9)'s optimum; unweighted, it held tiny-target triangles to relative accuracy
    # that the last stage had to undo (knight.off: (9) at the walk's end 24.60 against 21.05 at the optimum).
    from conftest import shared_mesh
    from sphere_nlp.solve import objective_value

    mesh = shared_mesh("knight.off")
    walk_end, finals = {}, {}
    for weighting in ("objective", "uniform"):
        ends = []

        def on_run(stage, nlp, run, ends=ends):
            if stage.startswith("area-continuation"):
                ends.append(nlp.unpack(run.x))

        settings = SolverSettings(on_run=on_run, area_continuation_weighting=weighting)
        result = sphere_nlp.parameterize(mesh, "original-areas", settings=settings, start="conformal")
        targets = make_targets("original-areas", result.input_vertices, result.faces,
                               np.bincount(result.faces.ravel()))
        walk_end[weighting] = objective_value(targets, *ends[-1])
        finals[weighting] = result.objective
    assert walk_end["objective"] <= 1.02 * finals["objective"]
    assert walk_end["uniform"] >= 1.1 * finals["uniform"]
    assert finals["objective"] <= finals["uniform"]


@pytest.mark.parametrize("mode", ["equal-areas", "original-areas"])
def test_an_area_mode_started_at_its_own_optimum_skips_the_walk(mode):
    # A start already near the area targets (here the optimum itself, as when a map is solved
    # again) goes straight to the margin stage with a small barrier: a few iterations to the same
    # optimum, where the walk would first move it away (its log-area steps are not (9)).
    from sphere_nlp.solve import start_area_distance

    V, F = ellipsoid(3, axes=(1.0, 4.0, 0.5))
    first = sphere_nlp.parameterize((V, F), target=mode, start="conformal")
    assert start_area_distance(first.excess, first.target_excess) <= SETTINGS.area_walk_distance
    again = sphere_nlp.parameterize((V, F), target=mode, start=first.vertices)
    assert [s["name"] for s in again.stages] == ["margin"]
    assert again.certificate.valid and again.max_constraint_violation <= 1e-8
    assert again.iterations <= 10 < first.iterations
    assert again.objective <= first.objective * (1 + 1e-6)
    # With the distance at 0 the walk always runs.
    walked = sphere_nlp.parameterize((V, F), target=mode, start=first.vertices,
                                     settings=SolverSettings(area_walk_distance=0.0))
    assert walked.stages[0]["name"].startswith("area-continuation")


@pytest.mark.parametrize("length", [30, 60])
def test_a_spike_maps_in_few_iterations(length):
    # A sphere of 162 vertices with one vertex pulled out 30 or 60 radii: its tip's five corners
    # target 0.6 and 0.3 degrees at weights 9,100 and 39,000, and must sum to 2 pi. Their targets
    # are shifted to sum to 2 pi (solve.summed_targets, the same minimiser): 73 and 106 iterations,
    # where the tip's pull made the margin stage run off or crawl (4,031 and 7,260 iterations).
    from sphere_nlp.solve import dropped_sum_drift

    V, F = spike_sphere(length)
    c = build_connectivity(F, len(V))
    drift = dropped_sum_drift(c, make_targets("original-angles", V, F, c.vertex_degree))
    assert np.flatnonzero(drift > SETTINGS.max_sum_drift).tolist() == [0]
    result = sphere_nlp.parameterize((V, F))
    assert result.success and result.converged
    assert certify(result.vertices, result.faces).valid
    assert result.iterations < 500
    # Every vertex sum holds at the end, the shifted tip's too.
    assert result.max_constraint_violation <= 1e-8


def test_the_size_cap_stops_a_stage_and_projects_its_iterate():
    # Without the caller's max_iter every run stops at the size's cap (here 20); a margin stage
    # stopped there is projected onto the constraints: certified, not optimal, and said so.
    from sphere_nlp.cli import summary_line
    from sphere_nlp.solve import stage_iteration_cap

    settings = SolverSettings(min_stage_iterations=20, stage_iterations_per_vertex=0.0, max_sum_drift=np.inf)
    assert stage_iteration_cap(162, settings) == 20
    result = sphere_nlp.parameterize(spike_sphere(30), settings=settings)
    assert result.success and not result.converged and result.status == "Maximum_Iterations_Exceeded"
    assert certify(result.vertices, result.faces).valid
    # (Without the shifted targets the margin stage runs off here and resumes, each run capped.)
    names = [s["name"] for s in result.stages]
    assert names[0] == "margin" and names[-1] == "projection" and set(names[1:-1]) <= {"margin-resumed"}
    assert all(s["iterations"] <= 20 for s in result.stages[:-1])
    assert result.stages[-2]["iteration_cap"] == 20
    assert result.iterations <= 3 * 20 + SETTINGS.projection_iterations
    assert "iteration cap for a mesh of this size (20 a stage" in summary_line("s.off", result)
    # The caller's max_iter replaces the cap (and reaching it fails, unless on_limit="project").
    with pytest.raises(sphere_nlp.SolveError, match="Maximum_Iterations_Exceeded"):
        sphere_nlp.parameterize(spike_sphere(30), settings=settings, max_iter=10)


def test_multipliers_started_at_zero_reach_the_same_optimum():
    # multiplier_estimate_max_vertices: large meshes start IPOPT's constraint multipliers at 0
    # instead of its least-squares estimate; where the optimum is attained, where it starts from
    # must not change it.
    V, F = ellipsoid(1, axes=(1.0, 2.0, 0.7))
    results = [sphere_nlp.parameterize((V, F), settings=SolverSettings(multiplier_estimate_max_vertices=limit))
               for limit in (len(V) + 1, len(V))]
    assert all(r.certificate.valid and r.converged for r in results)
    assert results[1].objective == pytest.approx(results[0].objective, rel=1e-9)
    assert np.abs(results[1].angles - results[0].angles).max() < 1e-6
