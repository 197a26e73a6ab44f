"""The area modes' authalic stage (sphere_nlp.authalic) and its polish by the NLP (sphere_nlp.polish)."""

import json
import math
import re
import subprocess
import sys
import warnings

import numpy as np
import pytest

from meshgen import COLLAPSING_LIMBS, ellipsoid, limbed_body, random_genus0_mesh, tentacle_creature
from sphere_nlp import authalic, parameterize, polish
from sphere_nlp.certify import certify
from sphere_nlp.connectivity import build_connectivity
from sphere_nlp.errors import SolveError
from sphere_nlp.geometry import signed_solid_angles
from sphere_nlp.settings import SolverSettings
from sphere_nlp.starts import angles_and_excess, starting_positions
from sphere_nlp.targets import make_targets

from conftest import MODELS


def _problem(V, F, mode="original-areas"):
    C = build_connectivity(F, len(V))
    start, _ = starting_positions(C, V)
    return C, start, make_targets(mode, V, F, C.vertex_degree)


def _tangent(X, seed=0):
    D = np.random.default_rng(seed).normal(size=X.shape)
    return D - np.einsum("ij,ij->i", D, X)[:, None] * X


def test_energy_gradient_matches_central_differences():
    V, F = ellipsoid(2)
    _, X, targets = _problem(V, F)
    energy = authalic.AuthalicEnergy(F, targets.excess, len(V))
    E, r = energy.value(X)
    G = energy.gradient(X, r)
    D = _tangent(X)
    h = 1e-6
    plus, minus = X + h * D, X - h * D
    plus /= np.linalg.norm(plus, axis=1, keepdims=True)
    minus /= np.linalg.norm(minus, axis=1, keepdims=True)
    numeric = (energy.value(plus)[0] - energy.value(minus)[0]) / (2 * h)
    assert np.isclose(numeric, np.sum(G * D), rtol=1e-6)
    # The gradient is tangent: moving along the radii does not change the energy.
    assert np.abs(np.einsum("ij,ij->i", G, X)).max() < 1e-12 * np.abs(G).max()


def test_energy_is_zero_at_the_targets_and_infinite_for_a_flipped_map():
    V, F = ellipsoid(2)
    X = V / np.linalg.norm(V, axis=1, keepdims=True)
    energy = authalic.AuthalicEnergy(F, signed_solid_angles(X, F), len(V))
    assert energy.value(X)[0] < 1e-24
    assert energy.value(X * np.array([-1.0, 1.0, 1.0]))[0] == math.inf     # mirrored: every triangle flipped


def test_descent_lowers_the_energy_every_step_and_ends_bijective():
    V, F = random_genus0_mesh(400, seed=3)
    C, start, targets = _problem(V, F)
    energy = authalic.AuthalicEnergy(F, targets.excess, len(V))
    X, trace = authalic.authalic_descent(start, F, targets.excess, max_steps=300)
    assert len(trace.energy) > 10
    assert np.all(np.diff(trace.energy) <= 0)
    assert trace.energy[-1] < 0.5 * energy.value(start)[0]
    assert certify(X, F).valid


def test_descent_reaches_areas_a_map_can_have():
    """Targets that a map has (the spherical areas of the ellipsoid's radial projection): from the
    conformal start, the descent gets every area within a fraction of a percent."""
    V, F = ellipsoid(2)
    X_true = V / np.linalg.norm(V, axis=1, keepdims=True)
    start, _ = starting_positions(build_connectivity(F, len(V)), V)
    X, trace = authalic.authalic_descent(start, F, signed_solid_angles(X_true, F), stall=1e-4)
    assert certify(X, F).valid
    assert trace.mean_abs_log_area[-1] < 1e-3 < authalic.mean_abs_log_area(start, F, signed_solid_angles(X_true, F))


def test_descent_past_its_steps_only_while_above_the_aim():
    """The budget's extra steps: a descent whose steps end above the aim goes on to the first step
    below it (the same iterates as a longer plain descent, cut there), one that ends below it stops
    at its steps."""
    V, F = ellipsoid(2)
    X_true = V / np.linalg.norm(V, axis=1, keepdims=True)
    start, _ = starting_positions(build_connectivity(F, len(V)), V)
    target = signed_solid_angles(X_true, F)
    _, plain = authalic.authalic_descent(start, F, target, stall=0.0, tolerance=0.0, max_steps=60)
    errors = np.array(plain.mean_abs_log_area)
    aim = float(errors[30])
    assert errors[4] > aim
    X, trace = authalic.authalic_descent(start, F, target, stall=0.0, tolerance=0.0, max_steps=5, aim=aim,
                                         extra_steps=100)
    assert trace.stopped == "aim" and len(trace.energy) == 31
    assert trace.mean_abs_log_area == plain.mean_abs_log_area[:31]
    assert certify(X, F).valid
    _, capped = authalic.authalic_descent(start, F, target, stall=0.0, tolerance=0.0, max_steps=5, aim=aim,
                                          extra_steps=10)
    assert capped.stopped == "steps" and len(capped.energy) == 15 and capped.mean_abs_log_area[-1] > aim
    _, below = authalic.authalic_descent(start, F, target, stall=0.0, tolerance=0.0, max_steps=40, aim=aim,
                                         extra_steps=100)
    assert below.stopped == "steps" and len(below.energy) == 40


def test_stretch_energy_step_moves_area_to_a_limbed_meshes_tentacles():
    """The conformal map shrinks the tentacles by orders of magnitude; SEM's global solves give them
    area back (kept only once certified, which the stage's untangling provides)."""
    V, F = tentacle_creature()
    C, start, targets = _problem(V, F)
    before = authalic.mean_abs_log_area(start, F, targets.excess)
    stage = authalic.authalic_map(V, F, start, targets.excess, max_time=30)
    assert certify(stage.positions, F).valid
    assert stage.sem_mean_abs_log_area < 0.5 * before
    assert stage.mean_abs_log_area <= min(stage.sem_mean_abs_log_area, before)


def test_the_authalic_stage_orders_its_solves_by_the_meshs_nested_dissection(monkeypatch):
    """SEM's solves (each restricted to its unknowns) and the descent's preconditioner are ordered
    by the mesh's nested dissection (from sparse_lu.NESTED_DISSECTION_UNKNOWNS vertices, lowered
    here), and reach the same map as with SuperLU's own order, to rounding."""
    from sphere_nlp import sparse_lu
    V, F = ellipsoid(3)
    C, start, targets = _problem(V, F)
    orderings = []
    factorize = sparse_lu.factorize
    monkeypatch.setattr(sparse_lu, "factorize", lambda A, ordering=None, **kw: (
        orderings.append(None if ordering is None else len(ordering)), factorize(A, ordering=ordering, **kw))[1])
    monkeypatch.setattr(sparse_lu, "NESTED_DISSECTION_UNKNOWNS", 0)
    ordered = authalic.authalic_map(V, F, start, targets.excess, max_steps=20, vertex_order=C.vertex_order())
    assert orderings and None not in orderings and len(V) in orderings and min(orderings) < len(V)
    monkeypatch.setattr(sparse_lu, "NESTED_DISSECTION_UNKNOWNS", 10 ** 9)
    del orderings[:]
    own = authalic.authalic_map(V, F, start, targets.excess, max_steps=20)
    assert orderings and set(orderings) == {None}
    assert certify(ordered.positions, F).valid
    assert np.abs(ordered.positions - own.positions).max() < 1e-8
    assert ordered.mean_abs_log_area == pytest.approx(own.mean_abs_log_area, rel=1e-8)


def test_no_worse_band_keeps_each_triangle_no_further_from_its_target():
    excess = np.array([0.5, 1.0, 3.0])
    target = np.array([1.0, 1.0, 1.0])
    lower, upper = polish.no_worse_band(excess, target, 0.0)
    # The authalic excess is on the band's edge, its mirror image about the target on the other.
    assert np.allclose(np.exp(lower), [0.5, 1.0, 1 / 3]) and np.allclose(np.exp(upper), [2.0, 1.0, 3.0])


def test_route_answer_is_never_worse_than_the_authalic_map():
    V, F = ellipsoid(3)
    C, _, targets = _problem(V, F)
    route = polish.authalic_route(C, V, targets, budget=polish.default_budget(len(V)))
    record = route.record
    assert certify(route.positions, F).valid
    assert record["mean_abs_log_area"] <= record["authalic"]["mean_abs_log_area"]
    assert record["objective"] <= record["authalic"]["objective"]
    # The answer's angles and excesses are those of its positions (both maps are placed maps).
    angles, excess = angles_and_excess(route.positions, F)
    assert np.abs(excess - route.solution.excess).max() < 1e-8


def test_route_keeps_the_authalic_map_when_the_polish_would_raise_the_area_error():
    """With a band wide enough to let (9)'s angle term trade area away, the polish ends at an area
    error above the authalic map's: the rule hands back the authalic map, and says why."""
    V, F = ellipsoid(2)
    C, _, targets = _problem(V, F)
    wide = SolverSettings(polish_slack=5.0)
    route = polish.authalic_route(C, V, targets, budget=None, settings=wide)
    record = route.record
    assert record["answer"] == "authalic"
    assert "raised the mean |log area ratio|" in record["reason"]
    assert np.allclose(route.positions, route.positions / np.linalg.norm(route.positions, axis=1)[:, None])
    assert record["mean_abs_log_area"] == pytest.approx(record["authalic"]["mean_abs_log_area"])
    assert not route.solution.converged and route.solution.success


def test_default_budget_is_counted_in_steps_and_iterations():
    settings = SolverSettings(authalic_steps=7, authalic_work=35_000, polish_iterations=3, min_polish_iterations=1)
    assert polish.default_budget(1000, settings) == {"descent_steps": 35, "extra_descent_steps": 105,
                                                     "polish_iterations": 3}
    assert polish.default_budget(10 ** 6, settings) == {"descent_steps": 7, "extra_descent_steps": 21,
                                                        "polish_iterations": 0}
    assert polish.default_budget(10, settings)["descent_steps"] == 70
    V, F = ellipsoid(3)
    C, _, targets = _problem(V, F)
    route = polish.authalic_route(C, V, targets, budget=polish.default_budget(len(V), settings), settings=settings)
    budget = polish.default_budget(len(V), settings)
    steps = route.record["authalic"]["descent_steps"]
    assert steps <= budget["descent_steps"] + budget["extra_descent_steps"]
    if steps > budget["descent_steps"]:
        # Past its steps only while above the aim, and it stopped there or at the extension's end.
        assert route.record["authalic"]["descent_stopped"] in ("aim", "steps", "stalled", "tolerance")
    assert all(stage["iterations"] <= 3 for stage in route.solution.stages if stage["name"] != "projection")
    assert certify(route.positions, F).valid


def test_area_mode_map_is_the_same_beside_a_busy_process():
    """The default budget counts work, not seconds: a CPU hog beside the run changes nothing."""
    V, F = ellipsoid(3)
    alone = parameterize((V, F), "original-areas")
    hog = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        busy = parameterize((V, F), "original-areas")
    finally:
        hog.kill()
        hog.wait()
    assert alone.success and busy.success
    assert np.array_equal(alone.vertices, busy.vertices)
    assert alone.area_route["answer"] == busy.area_route["answer"]


def test_authalic_stage_on_collapsed_triangles_is_quiet_and_certified(capfd):
    """A start whose thin limbs have collapsed past double precision (zero-area image triangles for
    SEM's cotangents): no RuntimeWarning, no native library's text, and a certified map back."""
    V, F = limbed_body(**COLLAPSING_LIMBS)
    C, start, targets = _problem(V, F)
    assert (signed_solid_angles(start, F) < 1e-25).any()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        stage = authalic.authalic_map(V, F, start, targets.excess, max_steps=50)
    assert certify(stage.positions, F).valid
    assert stage.mean_abs_log_area <= stage.start_mean_abs_log_area
    out, err = capfd.readouterr()
    assert out == "" and err == ""


def test_area_modes_default_to_the_route_with_its_budget():
    result = parameterize(str(MODELS / "cylinder.off"), "equal-areas")
    assert result.success and result.start == "authalic"
    assert result.area_route["budget"] == polish.default_budget(len(result.vertices))
    # equal-areas: the answer's areas are at least as even as the authalic map's.
    assert result.area_route["mean_abs_log_area"] <= result.area_route["authalic"]["mean_abs_log_area"]


def test_max_time_overrides_the_budget_and_inf_runs_the_polish_to_its_optimum():
    path = str(MODELS / "cylinder.off")
    limited = parameterize(path, "original-areas", max_time=4.0)
    assert limited.success and limited.area_route["budget"] is None
    assert limited.timings["total"] < 4.0 + 6.0             # the projection's grace at most
    unlimited = parameterize(path, "original-areas", max_time=math.inf)
    assert unlimited.area_route["budget"] is None
    assert unlimited.area_route["polish"]["converged"]


def test_start_conformal_keeps_the_nlp_route():
    result = parameterize(str(MODELS / "cylinder.off"), "original-areas", start="conformal")
    assert result.area_route is None and result.converged and result.start == "conformal"


def _cylinder_run_line(out, max_time):
    """The CLI's "wrote" line for the cylinder in original-areas with ``--max-time max_time``."""
    run = subprocess.run([sys.executable, "-m", "sphere_nlp", str(MODELS / "cylinder.off"), "--target",
                          "original-areas", "--max-time", max_time, "-o", str(out)],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    return [line for line in run.stderr.splitlines() if line.startswith("wrote")][-1]


def test_cli_max_time_none_and_the_run_line_names_the_answer(tmp_path):
    out = tmp_path / "c.sphere.off"
    last = _cylinder_run_line(out, "none")
    # In the map's terms: the solver's objective and statuses are the report's.
    assert re.search(r"; the (area-keeping map refined to the best map the solver finds"
                     r"|first area-keeping map, not refined: .*)$",
                     last) and "objective" not in last and "IPOPT" not in last
    assert out.is_file()


def test_the_run_line_under_a_time_limit_says_what_each_stage_took_of_its_share(tmp_path):
    last = _cylinder_run_line(tmp_path / "c.sphere.off", "60")
    match = re.search(r"; time: start ([\d.]+) s, area-keeping ([\d.]+) s of its ([\d.]+) s"
                      r"(?:, refinement ([\d.]+) s)?$", last)
    assert match, last
    # The area-keeping stage's share is three quarters of the time left after the start.
    assert float(match[2]) <= float(match[3]) + 0.1 and 30 < float(match[3]) <= 45


def test_both_steps_of_the_authalic_stage_report_progress():
    """SEM's solves and the descent's steps each report (the run's progress line every 2 s in a log)."""
    V, F = ellipsoid(2)
    _, start, targets = _problem(V, F)
    seen = []
    authalic.authalic_map(V, F, start, targets.excess, max_steps=5,
                          progress=lambda stage, step, energy, violation, seconds: seen.append((stage, step, energy)))
    stages = [stage for stage, _, _ in seen]
    assert "authalic SEM" in stages and stages.count("authalic descent") == 5
    assert all(np.isfinite(energy) for _, _, energy in seen)


def test_route_without_a_valid_start_fails_at_once_without_the_nlp(monkeypatch):
    # Where neither the conformal map's untangling nor the convex embedding gives a valid start (a
    # thin 50k body's tail below double precision), the route's answer cannot be certified; the
    # NLP alone from that start is no remedy (ten minutes, uncertified): the run fails, says why,
    # and solves nothing more.
    real = polish.starting_positions

    def folded(connectivity, vertices, **keywords):
        positions, _ = real(connectivity, vertices, **keywords)
        positions = positions.copy()
        positions[0] = -positions[0]                  # one vertex thrown across the sphere
        return positions, "embedding-uncentred"

    monkeypatch.setattr(polish, "starting_positions", folded)
    with pytest.raises(SolveError, match="^no valid starting map"):
        parameterize(str(MODELS / "cylinder.off"), "original-areas")
    result = parameterize(str(MODELS / "cylinder.off"), "original-areas", check=False)
    assert not result.success and not result.certificate.valid
    assert result.recovery is None and result.iterations == 0 and result.status == "No_Valid_Start"
    assert result.area_route["answer"] == "none"
    assert result.area_route["reason"].startswith("no valid starting map")
    from sphere_nlp.cli import failure_line
    assert failure_line(result).startswith("no valid starting map") and "nothing written" in failure_line(result)
    json.dumps(result.report(), allow_nan=False)
