"""Experiment: shift only the reduced Hessian's negative directions in an area-mode margin stage.

    python benchmarks/confined_shift.py ../shared/meshes/bunny.off original-areas
    python benchmarks/confined_shift.py ../shared/meshes/bunny.off original-areas --baseline

IPOPT makes its KKT matrix's inertia right by adding one multiple of the identity to the whole
Hessian. In the area modes' margin stage a few local non-convex spots (reduced-Hessian eigenvalues of
about -1e-3..-1e-2 on 16-62 variables each) set that shift, and it then damps every soft mode of the
rest of the mesh (curvature ~1e-3) to a fraction of its Newton step: the long tail of those stages
(docs/design.md, *Clipped Hessian*). This script tests the remedy with an oracle: at every Hessian
evaluation of the margin stage it finds the smallest eigenpairs of the reduced Hessian Z^T W Z (W the
Hessian handed to IPOPT, Z the constraints' null space) by shift-invert Lanczos on the KKT matrix, and
for each negative one adds 2 |lambda| / 0.95 to the diagonal on the variables that hold 95% of its
eigenvector, nothing elsewhere. It prints each IPOPT run (iterations, objective, how many iterations
IPOPT still shifted the whole Hessian) and the detection's cost. ``--baseline`` runs the same solve
unmodified. Not part of the package: the detection (SuperLU on the KKT matrix, 0.25-11 s an iteration
on 0.5k-5k vertices) costs far more than the iterations it saves; a cheap detection is the open step.
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

# Share of an eigenvector's squared entries that its shift covers.
SUPPORT_MASS = 0.95


def csc_from_casadi(sparsity, values):
    """scipy CSC matrix with a CasADi sparsity pattern and its nonzeros."""
    return sp.csc_matrix((values, np.array(sparsity.row()), np.array(sparsity.colind())),
                         shape=(sparsity.size1(), sparsity.size2()))


def negative_directions(hessian_upper, jacobian, sigma, n_pairs):
    """(eigenvalue, eigenvector) pairs of the reduced Hessian below zero, by shift-invert Lanczos.

    For v in the null space of J the KKT solve x = [W + sigma I, J^T; J, 0]^-1 [v; 0] is
    (Z^T (W + sigma I) Z)^-1 restricted to it, so its largest eigenvalues theta give the smallest
    reduced eigenvalues lambda = 1 / theta - sigma (those above -sigma).
    """
    W = hessian_upper + sp.triu(hessian_upper, 1).T
    n, m = W.shape[0], jacobian.shape[0]
    kkt = sp.bmat([[W + sigma * sp.identity(n), jacobian.T], [jacobian, -1e-12 * sp.identity(m)]], format="csc")
    lu = spla.splu(kkt, permc_spec="COLAMD")

    def solve(v):
        rhs = np.zeros(n + m)
        rhs[:n] = np.ravel(v)
        return lu.solve(rhs)[:n]

    # A fixed start vector: ARPACK's random one made the runs differ (knight 65-71 margin iterations).
    start = np.random.default_rng(0).standard_normal(n)
    theta, vectors = spla.eigsh(spla.LinearOperator((n, n), matvec=solve, dtype=float), k=n_pairs, which="LA",
                                tol=1e-3, maxiter=2000, v0=start)
    lam = 1.0 / np.maximum(theta, 1e-300) - sigma
    return [(value, vector) for value, vector in zip(lam, vectors.T) if value < -1e-7]


def main(argv=None):
    from sphere_nlp.api import parameterize
    from sphere_nlp.nlp import entry_positions
    from sphere_nlp.settings import SolverSettings

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("mesh")
    parser.add_argument("mode", choices=("equal-areas", "original-areas"))
    parser.add_argument("--sigma", type=float, default=0.2, help="shift of the shift-invert Lanczos (0.2)")
    parser.add_argument("--pairs", type=int, default=6, help="eigenpairs sought per iteration (6)")
    parser.add_argument("--factor", type=float, default=2.0, help="shift = factor |lambda| / 0.95 (2)")
    parser.add_argument("--baseline", action="store_true", help="the unmodified solve, for comparison")
    args = parser.parse_args(argv)

    state = {"log": []}
    diagonal_positions = {}              # per Hessian evaluator (one per NLP), the diagonal's entries

    def is_margin(stage):
        # The margin stage and its re-centred runs (and a penalty stage after it); not the walk's
        # steps, the equality fall-back or the projection.
        return stage.startswith(("margin", "penalty"))

    def confined_hessian(stage, evaluator, x, lam_f, lam_g, values):
        if not is_margin(stage) or args.baseline:
            return values
        start = time.perf_counter()
        if id(evaluator) not in diagonal_positions:
            pattern = csc_from_casadi(evaluator.hessian_sparsity, np.ones(len(values)))
            diagonal = np.arange(pattern.shape[0])
            diagonal_positions[id(evaluator)] = entry_positions(pattern, diagonal, diagonal)
        _, jacobian_values = evaluator.jacobian(x)
        jacobian = csc_from_casadi(evaluator.jacobian_sparsity, jacobian_values)
        hessian_upper = csc_from_casadi(evaluator.hessian_sparsity, values)
        shift = np.zeros(hessian_upper.shape[0])
        found = negative_directions(hessian_upper, jacobian, args.sigma, args.pairs)
        for value, vector in found:
            squares = vector ** 2
            order = np.argsort(-squares)
            support = order[:np.searchsorted(np.cumsum(squares[order]), SUPPORT_MASS) + 1]
            shift[support] = np.maximum(shift[support], args.factor * -value / SUPPORT_MASS)
        values = values.copy()
        values[diagonal_positions[id(evaluator)]] += shift
        state["log"].append((len(found), int(np.count_nonzero(shift)), time.perf_counter() - start))
        return values

    def report(stage, nlp, run):
        margin = is_margin(stage)
        shifted = sum(1 for size in (run.stats or {}).get("iterations", {}).get("regularization_size", [])[1:]
                      if size > 0)
        line = "%-28s %4d iterations  objective %.6f  %6.1f s  IPOPT shifted the whole Hessian on %d" % (
            run.status, run.iterations, run.objective, run.time_s, shifted)
        if state["log"]:
            log = np.array(state["log"])
            line += ("\n    confined shifts: negative directions on %d iterations, median %d variables shifted, "
                     "detection median %.2f s" % (np.count_nonzero(log[:, 0]), np.median(log[:, 1]), np.median(log[:, 2])))
        print(("margin  " if margin else "        ") + line, flush=True)
        state["log"] = []

    start = time.perf_counter()
    result = parameterize(args.mesh, args.mode, check=False,
                          settings=SolverSettings(on_run=report, modify_hessian=confined_hessian))
    print("%s: %s, %d iterations, objective %.6f, certified %s, %.1f s"
          % (Path(args.mesh).name, result.status, result.iterations, result.objective, result.certificate.valid,
             time.perf_counter() - start))


if __name__ == "__main__":
    main()
