"""The area modes' route: the authalic stage's map, then the NLP's polish of it under a budget.

The angle-space NLP converges slowly near an area-mode optimum from any start, while a first-order
authalic flow (:mod:`sphere_nlp.authalic`) reaches the same area accuracy in a fraction of the
time. So the area modes run:

1. the authalic stage: a certified map whose spherical areas are near the targets e';
2. the polish: the log-chord NLP of objective (9) started from that map, with each triangle's log
   excess kept within ``|log(e_a / e')| + polish_slack`` of log e' (:func:`no_worse_band`, e_a the
   authalic map's excess), so that it trades for (9)'s angle term only what it gains in area
   accuracy. It ends at IPOPT's optimum within the budget, else at its last iterate projected
   onto the constraints (``on_limit="project"``);
3. the never-worse rule: the polished map is the answer only if it certifies and neither its mean
   |log(e / e')| nor its objective (9) is above the authalic map's; otherwise the authalic map is.

:func:`authalic_route` runs the three and returns the answer as an
:class:`~sphere_nlp.solve.AngleSolution` with its positions and a record of both maps.

Examples
--------
>>> from sphere_nlp.shapes import cylinder
>>> from sphere_nlp.connectivity import build_connectivity
>>> from sphere_nlp.targets import make_targets
>>> V, F = cylinder()
>>> C = build_connectivity(F, len(V))
>>> route = authalic_route(C, V, make_targets("original-areas", V, F, C.vertex_degree), budget=default_budget(len(V)))
>>> route.record["answer"] in ("polished", "authalic"), route.solution.success
(True, True)
>>> route.record["mean_abs_log_area"] <= route.record["authalic"]["mean_abs_log_area"]
True
"""

import math
import time
from dataclasses import dataclass

import numpy as np

from . import interrupts, sparse_lu
from .authalic import authalic_map, mean_abs_log_area
from .certify import certify
from .settings import DEFAULT_SETTINGS
from .nlp import status_kind
from .solve import AngleSolution, max_constraint_violation, objective_value, solve_angles, without_valid_start
from .starts import angles_and_excess, starting_positions
from .unfold import sphere_positions


def default_budget(n_vertices, settings=DEFAULT_SETTINGS):
    """The area modes' default budget for a mesh of ``n_vertices``, counted in work:
    {"descent_steps", "extra_descent_steps", "polish_iterations"}.

    Steps and iterations, not seconds, so that a run's map depends on its input and options only,
    never on the machine or what else it is running (a wall-clock budget gave bunny.off a mean
    |log area ratio| of 0.006 alone and 0.111 beside two busy processes). A descent step costs
    about the same per vertex at every size, so a small mesh gets ``authalic_work / n`` steps (at
    most ten times ``authalic_steps``: knight.off, 502 vertices, needs 1,400 to reach 0.03 from
    its conformal start) and a large one ``authalic_steps``, both ending earlier below
    ``authalic_tolerance``. A descent whose steps end above :data:`AREA_AIM` goes on while it is
    above, for at most ``authalic_extension`` times its steps more: a body's thin limbs or tail,
    shrunk far below double precision's reach by the conformal start, take that long to open
    (``THIN_LIMBED_BODIES["31k"]``: 0.23 after its 300 steps, 0.03 after about 550). An IPOPT
    iteration of the polish costs
    more per vertex on a larger mesh, so the polish gets ``polish_work / n`` iterations, at most
    ``polish_iterations``, and none below ``min_polish_iterations``.

    >>> default_budget(500)
    {'descent_steps': 3000, 'extra_descent_steps': 9000, 'polish_iterations': 30}
    >>> default_budget(5000), default_budget(50000)["polish_iterations"]
    ({'descent_steps': 300, 'extra_descent_steps': 900, 'polish_iterations': 12}, 0)
    """
    n_vertices = max(int(n_vertices), 1)
    iterations = min(int(settings.polish_iterations), int(settings.polish_work // n_vertices))
    steps = max(int(settings.authalic_steps), min(int(settings.authalic_work // n_vertices),
                                                  10 * int(settings.authalic_steps)))
    return {"descent_steps": steps, "extra_descent_steps": int(settings.authalic_extension * steps),
            "polish_iterations": iterations if iterations >= settings.min_polish_iterations else 0}


def no_worse_band(excess, target_excess, slack):
    """Bounds (lower, upper) on log e that keep each |log(e / e')| within ``slack`` of its value at
    ``excess``: a triangle may move towards its target area, past it by as far as it was, and no
    further (``slack`` leaves room to one already at its target).

    >>> lower, upper = no_worse_band(np.array([2.0, 1.0]), np.array([1.0, 1.0]), 0.01)
    >>> np.round(np.exp([lower, upper]), 3).tolist()
    [[0.495, 0.99], [2.02, 1.01]]
    """
    log_target = np.log(target_excess)
    half = np.abs(np.log(excess) - log_target) + slack
    return log_target - half, log_target + half


@dataclass
class AreaRoute:
    """The answer of the area modes' route: ``solution`` (its angles, excesses, status, stages),
    ``positions`` (certified unit vectors), ``unfold_info`` (of the polished map's unfolding; empty
    for the authalic map, which is not unfolded), and ``record`` (JSON-safe: both maps'
    objective (9) and mean |log area ratio|, times, and which map is the answer, with why)."""
    solution: AngleSolution
    positions: np.ndarray
    unfold_info: dict
    record: dict


def authalic_route(connectivity, vertices, targets, budget=None, settings=None, progress=None, on_stage=None,
                   start=None, **solve_keywords):
    """Authalic stage, polish and never-worse rule (module docstring) within ``budget``.

    ``budget`` is a work budget (:func:`default_budget`: the descent's steps and the polish's IPOPT
    iterations per run); None means none: the authalic stage runs until it stalls and the polish to
    IPOPT's optimum. A wall-clock limit of the caller's (``interrupts.deadline``, the run's
    ``max_time``) bounds both stages as well, the authalic one to ``settings.authalic_share`` of
    the time left. ``solve_keywords`` go to :func:`~sphere_nlp.solve.solve_angles` (ipopt_options,
    max_iter, corner_floor, area_floor). ``on_stage(name)`` is called with "authalic" and "polish".
    ``start`` (positions, kind): the starting map already found (:func:`starting_positions`).
    """
    settings = DEFAULT_SETTINGS if settings is None else settings
    faces = connectivity.faces
    began = time.perf_counter()
    if on_stage is not None:
        on_stage("authalic")
    start, start_kind = (starting_positions(connectivity, vertices, progress=progress) if start is None
                         else start)
    start_s = time.perf_counter() - began
    start_certificate = certify(start, faces)
    if not start_certificate.valid:
        return _without_valid_start(connectivity, targets, start, start_kind, start_certificate, start_s)
    left = interrupts.seconds_left()
    stage_time = None if math.isinf(left) else settings.authalic_share * left
    stage = authalic_map(vertices, faces, start, targets.excess, max_time=stage_time,
                         max_steps=None if budget is None else budget["descent_steps"],
                         tolerance=1e-4 if budget is None else settings.authalic_tolerance,
                         stall=settings.authalic_stall, progress=progress,
                         aim=None if budget is None else AREA_AIM,
                         extra_steps=0 if budget is None else budget["extra_descent_steps"],
                         vertex_order=(connectivity.vertex_order()
                                       if connectivity.n_vertices >= sparse_lu.NESTED_DISSECTION_UNKNOWNS else None))
    authalic_angles, authalic_excess = angles_and_excess(stage.positions, faces)
    authalic_objective = objective_value(targets, authalic_angles, authalic_excess)
    record = {"start": start_kind, "start_seconds": round(start_s, 3),
              "authalic": {"seconds": round(stage.seconds, 3), "sem_seconds": round(stage.sem_seconds, 3),
                           "descent_steps": stage.steps, "descent_stopped": stage.trace.stopped,
                           "objective": authalic_objective,
                           "mean_abs_log_area": stage.mean_abs_log_area,
                           "start_mean_abs_log_area": stage.start_mean_abs_log_area,
                           "sem_mean_abs_log_area": stage.sem_mean_abs_log_area,
                           "share_s": None if stage_time is None else round(stage_time, 3)}}
    polish_began = time.perf_counter()
    polished = None
    no_polish = "no time left for the polish"
    if budget is not None and budget["polish_iterations"] == 0:
        no_polish = "the budget leaves no iterations to refine a mesh this size"
    elif not interrupts.deadline_passed():
        if on_stage is not None:
            on_stage("polish")
        band = no_worse_band(authalic_excess, targets.excess, settings.polish_slack)
        left = interrupts.seconds_left()
        if budget is not None:
            asked = solve_keywords.get("max_iter")
            solve_keywords["max_iter"] = min(budget["polish_iterations"], asked or budget["polish_iterations"])
        # No walk towards the targets first: the band already keeps the polish near them.
        polished = solve_angles(connectivity, targets, start=stage.positions, vertices=vertices,
                                on_limit="project", excess_band=band, progress=progress,
                                settings=settings.replace(area_walk_distance=math.inf),
                                max_time=None if math.isinf(left) else left, **solve_keywords)
    answer, reason, positions, unfold_info = "authalic", no_polish, stage.positions, {}
    if polished is not None:
        reason = _rejection(polished, targets, stage.mean_abs_log_area, authalic_objective)
        if reason is None:
            candidate, info = sphere_positions(connectivity, polished.angles, polished.excess)
            error = mean_abs_log_area(candidate, faces, targets.excess)
            if not certify(candidate, faces).valid:
                reason = "the polished map failed its certificate"
            elif _raised(error, stage.mean_abs_log_area):
                reason = "the polish raised the mean |log area ratio|"
            else:
                answer, reason, positions, unfold_info = "polished", None, candidate, info
    if answer == "polished":
        solution = polished
    else:
        solution = AngleSolution(
            angles=authalic_angles, excess=authalic_excess, success=True,
            status=polished.status if polished is not None else "Not_Polished",
            iterations=polished.iterations if polished is not None else 0, objective=authalic_objective,
            max_constraint_violation=max_constraint_violation(connectivity, authalic_angles, authalic_excess),
            stages=polished.stages if polished is not None else [], initial_angles=authalic_angles,
            initial_excess=authalic_excess, start="authalic", converged=False)
    record.update({
        "answer": answer, "reason": reason, "budget": budget,
        "polish": None if polished is None else {
            "status": polished.status, "converged": bool(polished.converged), "iterations": polished.iterations,
            "objective": polished.objective, "seconds": round(time.perf_counter() - polish_began, 3)},
        "objective": solution.objective, "mean_abs_log_area": mean_abs_log_area(positions, faces, targets.excess),
        "seconds": round(time.perf_counter() - began, 3)})
    solution.start = "authalic"
    return AreaRoute(solution=solution, positions=positions, unfold_info=unfold_info, record=record)


def _without_valid_start(connectivity, targets, start, start_kind, certificate, start_s):
    """The route's answer when no start is valid: the conformal map's flipped triangles could not
    be untangled and the convex embedding collapsed too (thin parts below double precision), so
    there is nothing to descend from or polish; a failed solution that says so."""
    reason = ("no valid starting map: the conformal map could not be untangled and the convex embedding has "
              "%s (parts too thin for double precision)" % certificate.reason)
    solution = without_valid_start(connectivity, targets, start, "authalic")
    record = {"start": start_kind, "start_seconds": round(start_s, 3), "authalic": None, "answer": "none",
              "reason": reason, "budget": None, "polish": None, "objective": None, "mean_abs_log_area": None,
              "seconds": round(start_s, 3)}
    return AreaRoute(solution=solution, positions=start, unfold_info={}, record=record)


def _rejection(polished, targets, authalic_error, authalic_objective):
    """Why the polish's angles are not the answer before they are unfolded, or None."""
    if not polished.success:
        if status_kind(polished.status) == "limit":
            return "the budget ended before the polish's iterate was projected onto the constraints"
        return "the polish failed (IPOPT %s)" % polished.status
    if polished.objective > authalic_objective:
        return "the polish did not lower objective (9)"
    error = float(np.mean(np.abs(np.log(polished.excess / targets.excess))))
    if _raised(error, authalic_error):
        return "the polish raised the mean |log area ratio|"
    return None


def _raised(error, before):
    """Whether an area error is above ``before`` by more than the unfolding's rounding."""
    return error > before * (1 + 1e-9)


# The run line's words for why the first area-keeping map is the answer (record["reason"] keeps
# the solver's words, for --report).
_PLAIN_REASONS = {
    "no time left for the polish": "no time was left to refine it",
    "the budget leaves no iterations to refine a mesh this size":
        "the default budget does not refine a mesh this size (--max-time S or none does)",
    "the budget ended before the polish's iterate was projected onto the constraints":
        "the time limit ended before its refinement was done",
    "the polished map failed its certificate": "the refined map failed its certificate",
    "the polish raised the mean |log area ratio|": "refining it would have made the areas worse",
    "the polish did not lower objective (9)": "refining it did not improve it",
}


# The mean |log area ratio| the area modes aim for; a run line above it says why and what would help.
AREA_AIM = 0.03

# Why the authalic stage's descent stopped (DescentTrace.stopped), in the run line's words.
_DESCENT_ENDS = {
    "steps": "the area-keeping stage used its budget of steps (--max-time none runs it until it stalls)",
    "time": "--max-time ended the area-keeping stage (a longer --max-time gives it more)",
    "stalled": "the area-keeping stage stalled there",
    "no step lowers the energy": "the area-keeping stage found no step that lowers its error",
}


def describe(record):
    """One clause for the run's line, in the map's terms: the first area-keeping map as it is, or
    refined (to the best map, or as far as the budget allowed), and why; above :data:`AREA_AIM`, why
    the areas are not nearer and what would bring them nearer. The solver's own account
    (objective (9), IPOPT's status and iterations) is the record's, in ``--report``."""
    authalic = record["authalic"]
    stopped = authalic.get("descent_stopped", "")
    if (authalic["descent_steps"] == 0
            and authalic["mean_abs_log_area"] >= authalic["start_mean_abs_log_area"] * (1 - 1e-9)):
        kind = "conformal" if record.get("start", "").startswith("conformal") else "convex-embedding"
        clause = ("the %s start as it is: the %s before the area-keeping stage could change it"
                  % (kind, "time limit ended" if stopped == "time" else "start's smallest triangles are too small "
                     "for double precision" if stopped.startswith("a triangle") else "area-keeping stage stopped"))
    elif record["answer"] == "polished":
        clause = ("the area-keeping map refined to the best map the solver finds" if record["polish"]["converged"]
                  else "the area-keeping map refined as far as the budget allowed (mean |log area ratio| %.3g "
                  "before; --max-time none refines it to the end)" % authalic["mean_abs_log_area"])
    else:
        reason = record["reason"]
        plain = _PLAIN_REASONS.get(reason, "its refinement failed" if reason.startswith("the polish failed")
                                   else reason)
        clause = "the first area-keeping map, not refined: %s (--report has the details)" % plain
    if record["mean_abs_log_area"] > AREA_AIM and authalic["descent_steps"]:
        clause += "; above the %.2g aimed for: %s" % (
            AREA_AIM, _DESCENT_ENDS.get(stopped, "the start's smallest triangles are too small for double "
                                        "precision (thin limbs), which the area-keeping stage cannot undo"))
    if record.get("instead_of"):
        clause = ("%s instead of %s, whose map would shrink this shape's thin limbs or tail past what "
                  "double precision holds: %s" % (record["mode"], record["instead_of"], clause))
    if authalic.get("share_s") is not None:
        # Under a time limit: what each stage took, the area-keeping one against its share of it.
        clause += "; time: start %.1f s, area-keeping %.1f s of its %.1f s" % (
            record["start_seconds"], authalic["seconds"], authalic["share_s"])
        if record.get("polish"):
            clause += ", refinement %.1f s" % record["polish"]["seconds"]
    return clause
