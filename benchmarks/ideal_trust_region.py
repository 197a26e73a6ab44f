"""Experiment: how many iterations would an ideal trust-region interior method need for the area modes?

    python benchmarks/ideal_trust_region.py ../shared/meshes/knight.off original-areas

IPOPT shifts the whole Hessian when the reduced Hessian has negative curvature anywhere, and the area
modes' margin stage then takes hundreds of iterations (docs/design.md, "Where the area modes'
iterations go"). A trust-region interior method (Byrd, Gilbert & Nocedal 2000; KNITRO's interior/CG)
instead follows negative curvature inside its region. This script bounds what such a method could
gain: it solves the same margin-stage NLP (objective, constraints, bounds, start) by a barrier method
whose every step solves its trust-region subproblem *exactly*, by a dense eigen-decomposition of the
reduced Hessian (Byrd-Omojokun split: a normal step towards c = 0, then the exact minimiser of the
quadratic model over the constraints' null space, in slack-scaled variables, l2 merit with
second-order correction). A practical method (Steihaug CG with projections) takes at least as many
iterations, each costing more. Dense linear algebra limits it to small meshes (knight.off: 4,000
unknowns). It prints, for IPOPT's margin run and this method, the iterations needed to come within
1e-3 and 1e-6 (relative) of IPOPT's final objective at violation <= 1e-8, and the final point.
Not part of the package: on knight.off original-areas it took 71 accepted steps and 10 rejected ones
(first barrier 0.1) and 114 and 7 (1e-4) against IPOPT's 71 iterations, its trust radius 0.06-1, to
21.620 against IPOPT's 21.054; on tests/meshgen.py's tentacle_creature() 23 and 3 against 26, to the
same optimum (docs/design.md, "Where
the area modes' iterations go").
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import scipy.linalg as sla

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from confined_shift import csc_from_casadi            # noqa: E402 (benchmarks/, beside this script)
from trust_region_probe import capture_margin_stage, symmetric   # noqa: E402


def exact_trust_region_step(gradient, hessian, radius):
    """argmin g.p + p.H p / 2 over |p| <= radius, by eigen-decomposition (Moré & Sorensen 1983)."""
    values, vectors = np.linalg.eigh(hessian)
    gamma = vectors.T @ gradient

    def step(sigma):
        return -gamma / (values + sigma)

    if values[0] > 0:
        p = step(0.0)
        if np.linalg.norm(p) <= radius:
            return vectors @ p
    low = max(0.0, -values[0]) + 1e-14 * max(1.0, abs(values[0]))
    if np.linalg.norm(step(low)) < radius:           # the hard case: add a move along the lowest mode
        p = step(low)
        p[0] += np.sqrt(max(radius ** 2 - p @ p, 0.0))
        return vectors @ p
    high = low + np.linalg.norm(gamma) / radius + 1.0
    for _ in range(200):                             # bisection on the secular equation |p(sigma)| = r
        middle = 0.5 * (low + high)
        if np.linalg.norm(step(middle)) > radius:
            low = middle
        else:
            high = middle
        if high - low <= 1e-12 * max(1.0, high):
            break
    return vectors @ step(high)


class BarrierProblem:
    """f, c and derivatives of the margin-stage NLP with its bounds l <= x <= h."""

    def __init__(self, nlp, lower, upper):
        self.values, self.n_eq = nlp._numeric, nlp.n_equalities
        self.lower, self.upper = lower, upper
        self.has_lower, self.has_upper = np.isfinite(lower), np.isfinite(upper)

    def f_c(self, x):
        f, g = self.values.objective_and_constraints(x)
        return f, np.asarray(g)[:self.n_eq]

    def derivatives(self, x):
        _, gradient = self.values.gradient(x)
        jacobian = csc_from_casadi(self.values.jacobian_sparsity, self.values.jacobian(x)[1]).tocsr()[:self.n_eq]
        return np.asarray(gradient), jacobian.toarray()

    def hessian(self, x, lam):
        return symmetric(csc_from_casadi(self.values.hessian_sparsity,
                                         self.values.hessian(x, 1.0, lam))).toarray()

    def slacks(self, x):
        low = np.where(self.has_lower, x - np.where(self.has_lower, self.lower, 0), np.inf)
        high = np.where(self.has_upper, np.where(self.has_upper, self.upper, 0) - x, np.inf)
        return low, high

    def barrier(self, x, mu):
        low, high = self.slacks(x)
        if (low <= 0).any() or (high <= 0).any():
            return np.inf
        return -mu * (np.log(low[self.has_lower]).sum() + np.log(high[self.has_upper]).sum())


def solve(problem, x, mu, max_iter=400, tol=1e-8, report=print):
    """The barrier method; returns (x, Newton steps, history of (steps so far, objective, violation))."""
    low, high = problem.slacks(x)
    z_low = np.where(problem.has_lower, mu / low, 0.0)
    z_high = np.where(problem.has_upper, mu / high, 0.0)
    radius, nu, tau = 1.0, 1.0, 0.995
    history = []
    steps, rejected = 0, 0                                      # accepted and rejected trial steps
    f, c = problem.f_c(x)
    for iteration in range(max_iter):
        gradient, A = problem.derivatives(x)
        low, high = problem.slacks(x)
        scale = np.minimum(1.0, np.minimum(low, high))          # affine scaling by the slacks
        grad_phi = gradient - np.where(problem.has_lower, mu / low, 0) + np.where(problem.has_upper, mu / high, 0)
        AS = A * scale
        Q, R = sla.qr(AS.T, mode="full")                        # (AS)^T = Q R
        m = A.shape[0]
        Q1, Z, R1 = Q[:, :m], Q[:, m:], R[:m]
        lam = -sla.solve_triangular(R1, Q1.T @ (scale * grad_phi))   # least-squares multipliers
        dual = gradient + A.T @ lam - z_low + z_high
        violation = np.abs(c).max()
        low_finite, high_finite = np.where(problem.has_lower, low, 0), np.where(problem.has_upper, high, 0)
        complementarity = max((z_low * low_finite).max(), (z_high * high_finite).max())
        history.append((steps, f, violation))
        error_mu = max(np.abs(dual).max() / max(1.0, np.abs(z_low).max() / 100),
                       violation,
                       np.abs(np.where(problem.has_lower, z_low * low_finite - mu, 0)).max(),
                       np.abs(np.where(problem.has_upper, z_high * high_finite - mu, 0)).max())
        if iteration % 10 == 0:
            report("  step %3d  f %.10f  viol %.1e  dual %.1e  compl %.1e  mu %.0e  radius %.1e"
                   % (steps, f, violation, np.abs(dual).max(), complementarity, mu, radius))
        if mu <= tol / 10 and error_mu <= tol and violation <= tol:
            break
        if error_mu <= 10 * mu and mu > tol / 10:
            mu = max(tol / 10, min(0.2 * mu, mu ** 1.5))
            continue
        W = problem.hessian(x, lam)
        sigma = np.where(problem.has_lower, z_low / low, 0) + np.where(problem.has_upper, z_high / high, 0)
        W[np.diag_indices_from(W)] += sigma
        H = (W * scale).T * scale                               # S W S
        g = scale * grad_phi
        # normal step: least-norm solution of A S d = -c, held within 0.8 radius
        normal = -Q1 @ sla.solve_triangular(R1, c, trans="T")
        if np.linalg.norm(normal) > 0.8 * radius:
            normal *= 0.8 * radius / np.linalg.norm(normal)
        rest = np.sqrt(max(radius ** 2 - normal @ normal, 0.0))
        p = exact_trust_region_step(Z.T @ (g + H @ normal), Z.T @ H @ Z, rest)
        step = normal + Z @ p
        # fraction to the boundary (the scaled step of a slack-scaled unknown is its relative move)
        d = scale * step
        alpha = 1.0
        with np.errstate(divide="ignore", invalid="ignore"):
            shrink = np.concatenate([(-tau * low / d)[problem.has_lower & (d < 0)],
                                     (tau * high / d)[problem.has_upper & (d > 0)]])
        if shrink.size:
            alpha = min(1.0, shrink.min())
        step, d = alpha * step, alpha * d
        linear = c + A @ d
        vpred = np.linalg.norm(c) - np.linalg.norm(linear)
        q = g @ step + 0.5 * step @ H @ step
        if vpred > 0:
            nu = max(nu, q / (0.9 * vpred) + 1e-8) if q > 0 else nu
        pred = -q + nu * vpred
        merit = f + problem.barrier(x, mu) + nu * np.linalg.norm(c)
        accepted = False
        for trial in (d, None):
            if trial is None:                               # second-order correction
                _, c_trial = problem.f_c(x + d)
                if not np.isfinite(c_trial).all():
                    continue
                trial = d + scale * (-Q1 @ sla.solve_triangular(R1, c_trial, trans="T"))
            f_new, c_new = problem.f_c(x + trial)
            barrier_new = problem.barrier(x + trial, mu)
            if not np.isfinite(f_new) or not np.isfinite(barrier_new):
                continue
            ratio = (merit - (f_new + barrier_new + nu * np.linalg.norm(c_new))) / max(pred, 1e-300)
            if ratio >= 1e-4:
                accepted = True
                break
        norm = np.linalg.norm(step)
        if not accepted:
            rejected += 1
            radius = 0.25 * norm
            if radius < 1e-14:
                report("  trust region collapsed")
                break
            continue
        if ratio > 0.75 and norm >= 0.9 * radius:
            radius = min(2 * radius, 1e3)
        elif ratio < 0.25:
            radius = 0.5 * norm
        x = x + trial
        f, c = f_new, c_new
        steps += 1
        # primal-dual update of the bound multipliers, kept within a factor 10 of mu / slack
        low_new, high_new = problem.slacks(x)
        z_low = np.where(problem.has_lower, np.clip(z_low + (mu / low - z_low - z_low / low * trial),
                                                    mu / (10 * low_new), 10 * mu / low_new), 0.0)
        z_high = np.where(problem.has_upper, np.clip(z_high + (mu / high - z_high + z_high / high * trial),
                                                     mu / (10 * high_new), 10 * mu / high_new), 0.0)
    report("  %d accepted steps, %d rejected" % (steps, rejected))
    return x, steps, history


def first_within(history, reference, relative):
    for iteration, f, violation in history:
        if violation <= 1e-8 and abs(f - reference) <= relative * abs(reference):
            return iteration
    return None


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("mesh")
    parser.add_argument("mode")
    parser.add_argument("--mu", type=float, default=None, help="first barrier parameter (IPOPT's stage's mu_init)")
    parser.add_argument("--max-iter", type=int, default=400)
    args = parser.parse_args(argv)

    ipopt_history = []

    def on_iterate(stage, iteration, x, lam_g, lam_x, objective):
        if stage == "margin" and len(ipopt_history) == iteration:
            ipopt_history.append((iteration, float(objective), x.copy()))

    start = time.perf_counter()
    result, margin = capture_margin_stage(args.mesh, args.mode, on_iterate=on_iterate, check=False)
    run, nlp, x0, keywords = margin["run"], margin["nlp"], margin["x0"], margin["keywords"]
    lbx, ubx, _, _ = margin["bounds"]
    print("whole solve: %s, %d iterations, objective %.6f, %.1f s" % (
        result.status, result.iterations, result.objective, time.perf_counter() - start))
    problem = BarrierProblem(nlp, lbx, ubx)
    history = [(i, f, np.abs(problem.f_c(x)[1]).max()) for i, f, x in ipopt_history[:run.iterations + 1]]
    reference = run.objective
    print("IPOPT margin run: %s, %d iterations, objective %.8f; within 1e-3 at iteration %s, 1e-6 at %s"
          % (run.status, run.iterations, reference, first_within(history, reference, 1e-3),
             first_within(history, reference, 1e-6)))
    options = keywords.get("options") or {}
    mu = args.mu if args.mu is not None else float(options.get("mu_init", 0.1))
    x = np.array(x0, float)
    push = 1e-8 * np.maximum(1.0, np.abs(lbx))
    x = np.where(np.isfinite(lbx), np.maximum(x, lbx + push), x)
    x = np.where(np.isfinite(ubx), np.minimum(x, ubx - push), x)
    print("ideal trust-region barrier method from the same start, mu %.0e, %d unknowns, %d constraints"
          % (mu, len(x), problem.n_eq))
    clock = time.perf_counter()
    x, iterations, history = solve(problem, x, mu, max_iter=args.max_iter)
    f, c = problem.f_c(x)
    print("ideal trust region: %d steps, objective %.8f, violation %.1e, %.1f s; within 1e-3 of IPOPT's "
          "objective at step %s, 1e-6 at %s; within 1e-3 of its own at %s"
          % (iterations, f, np.abs(c).max(), time.perf_counter() - clock, first_within(history, reference, 1e-3),
             first_within(history, reference, 1e-6), first_within(history, f, 1e-3)))


if __name__ == "__main__":
    main()
