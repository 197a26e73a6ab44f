"""Experiment: an area-mode margin stage solved by a trust-region method instead of IPOPT.

    python benchmarks/trust_region_probe.py ../shared/meshes/knight.off original-areas

IPOPT shifts the whole Hessian by one multiple of the identity when the reduced Hessian has negative
curvature anywhere, and the area modes' margin stage then crawls (docs/design.md, "Where the area
modes' iterations go"). A trust-region method handles negative curvature inside its region instead
(truncated CG stops on it and steps to the boundary). This script runs the usual solve up to the
margin stage, then solves that stage's NLP (the same objective, constraints and bounds, from the
same start) with scipy's ``trust-constr`` (Byrd-Omojokun SQP inside a barrier on the bounds, projected
CG), and prints both: iterations, objective, constraint violation, time. Not part of the package:
on knight.off original-areas trust-constr stops moving after five accepted steps (zero steps, its
trust region meeting the barrier's slack bounds) at objective 22.5 and violation 0.3, where IPOPT's
stage takes 71 iterations to 21.054; a trust-region interior method that holds up here would have
to be written.
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import scipy.optimize as so
import scipy.sparse as sp

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


from confined_shift import csc_from_casadi     # noqa: E402 (benchmarks/, beside this script)


def symmetric(upper):
    """The whole symmetric matrix from its upper triangle (CasADi's Hessian pattern)."""
    return (upper + sp.triu(upper, 1).T).tocsr()


def capture_stages(mesh, mode, names, on_iterate=None, **keywords):
    """``parameterize(mesh, mode, **keywords)``, and what the first IPOPT run of each named stage was given.

    Returns the result and a dict from each name in ``names`` that ran (e.g. "margin",
    "area-continuation-1") to a dict: the stage's ``nlp`` (LogChordNLP), its ``run`` (IpoptRun), its
    start ``x0``, the ``keywords`` of its ``nlp.solve`` call (bounds, options, warm start), as the
    solve set them, and the ``bounds`` (lbx, ubx, lbg, ubg) those keywords gave the run.
    ``on_iterate`` is SolverSettings' hook (stage, iteration, x, lam_g, lam_x, objective).
    """
    from sphere_nlp.api import parameterize
    from sphere_nlp.nlp import LogChordNLP
    from sphere_nlp.settings import SolverSettings

    calls, captured = {}, {}
    real_solve = LogChordNLP.solve

    def recording_solve(self, x0, **solve_keywords):
        # each NLP's latest run: its start and keywords
        calls[id(self)] = (np.array(x0, float), dict(solve_keywords))
        return real_solve(self, x0, **solve_keywords)

    def on_run(stage, nlp, run):
        if stage in names and stage not in captured:
            x0, solve_keywords = calls[id(nlp)]
            bounds = nlp._bounds(solve_keywords.get("inequalities", False), solve_keywords.get("excess_bounds"),
                                 solve_keywords.get("log_u_lower"))
            captured[stage] = dict(nlp=nlp, run=run, x0=x0, keywords=solve_keywords, bounds=bounds)

    LogChordNLP.solve = recording_solve
    try:
        result = parameterize(mesh, mode, settings=SolverSettings(on_run=on_run, on_iterate=on_iterate), **keywords)
    finally:
        LogChordNLP.solve = real_solve
    return result, captured


def capture_margin_stage(mesh, mode, on_iterate=None, **keywords):
    """:func:`capture_stages` for the first margin stage: (result, its dict)."""
    result, captured = capture_stages(mesh, mode, ("margin",), on_iterate=on_iterate, **keywords)
    return result, captured["margin"]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("mesh")
    parser.add_argument("mode")
    parser.add_argument("--maxiter", type=int, default=3000)
    parser.add_argument("--radius", type=float, default=0.1)
    args = parser.parse_args(argv)

    start = time.perf_counter()
    result, margin = capture_margin_stage(args.mesh, args.mode, check=False)
    run = margin["run"]
    print("whole solve: %s, %d iterations, objective %.6f, %.1f s" % (
        result.status, result.iterations, result.objective, time.perf_counter() - start))
    print("IPOPT margin run: %s, %d iterations, objective %.8f, %.1f s" % (
        run.status, run.iterations, run.objective, run.time_s))

    nlp, x0 = margin["nlp"], margin["x0"]
    lbx, ubx, lbg, ubg = margin["bounds"]
    n_eq = nlp.n_equalities
    values = nlp._numeric
    counts = {"hess": 0, "nan": 0}

    def fun(x):
        f = values.objective_and_constraints(x)[0]
        counts["nan"] += not np.isfinite(f)
        return f if np.isfinite(f) else 1e30

    def grad(x):
        return values.gradient(x)[1]

    def hess_f(x):
        counts["hess"] += 1
        return symmetric(csc_from_casadi(values.hessian_sparsity, values.hessian(x, 1.0, np.zeros(n_eq))))

    def cons(x):
        return values.objective_and_constraints(x)[1][:n_eq]

    def jac(x):
        return csc_from_casadi(values.jacobian_sparsity, values.jacobian(x)[1]).tocsr()[:n_eq]

    def hess_g(x, v):
        return symmetric(csc_from_casadi(values.hessian_sparsity, values.hessian(x, 0.0, np.asarray(v))))

    # the start strictly inside the bounds, as a barrier method needs
    x_start = np.clip(x0, lbx + 1e-9, ubx - 1e-9)
    start = time.perf_counter()
    out = so.minimize(fun, x_start, jac=grad, hess=hess_f, method="trust-constr",
                      bounds=so.Bounds(lbx, ubx),
                      constraints=[so.NonlinearConstraint(cons, lbg[:n_eq], ubg[:n_eq], jac=jac, hess=hess_g)],
                      options={"maxiter": args.maxiter, "gtol": 1e-8, "xtol": 1e-12, "verbose": 0,
                               "initial_barrier_parameter": 1e-4, "initial_tr_radius": args.radius})
    print("trust-constr: %s (status %d), %d iterations, %d Hessians, objective %.8f, max violation %.2e, "
          "CG iterations %d, %.1f s, non-finite objectives %d" % (
              out.message, out.status, out.nit, counts["hess"], out.fun, np.abs(cons(out.x)).max(),
              out.cg_niter, time.perf_counter() - start, counts["nan"]))


if __name__ == "__main__":
    main()
