"""Experiment: is the area modes' long margin stage the barrier's doing?

    python benchmarks/restart_probe.py ../shared/meshes/hand_closed.obj original-areas --every 40

Runs the usual solve, keeping the margin stage's iterate (x and multipliers) every ``--every``
iterations, then restarts that stage's NLP (the same bounds and options) from each kept iterate,
warm-started from its multipliers with a small barrier (``--mu``), and prints how many iterations
each restart takes to converge and to what objective. If the stage's length came from IPOPT's
barrier schedule, a restart with a small barrier from late iterates would converge in a few
iterations. Not part of the package: on hand_closed.obj original-areas (margin stage 233
iterations to 144.910) the restarts take about as many iterations as the stage had left (from
iteration 120: 111 with mu 1e-4, 121 with 1e-7; from 200: 40 and 34), and on knight.off (71
iterations: from 20, 55 and 49; from 60, 12 and 10), so it is not (docs/design.md, "Where the area
modes' iterations go").
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from trust_region_probe import capture_margin_stage     # noqa: E402 (benchmarks/, beside this script)


def main(argv=None):
    from sphere_nlp.settings import WARM_START_OPTIONS

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("mesh")
    parser.add_argument("mode")
    parser.add_argument("--every", type=int, default=40, help="keep every K-th margin iterate (40)")
    parser.add_argument("--mu", type=float, nargs="+", default=[1e-4, 1e-7],
                        help="initial barrier parameters of the restarts (1e-4 1e-7)")
    args = parser.parse_args(argv)

    kept = []

    def on_iterate(stage, iteration, x, lam_g, lam_x, objective):
        if stage == "margin" and iteration > 0 and iteration % args.every == 0:
            kept.append((iteration, float(objective), np.array(x), np.array(lam_g), np.array(lam_x)))

    start = time.perf_counter()
    result, margin = capture_margin_stage(args.mesh, args.mode, on_iterate=on_iterate)
    run = margin["run"]
    print("whole solve: %s, %d iterations, objective %.6f, %.1f s" % (
        result.status, result.iterations, result.objective, time.perf_counter() - start))
    print("margin stage: %s, %d iterations, objective %.6f" % (run.status, run.iterations, run.objective))

    nlp = margin["nlp"]
    for iteration, objective, x, lam_g, lam_x in kept:
        for mu in args.mu:
            keywords = dict(margin["keywords"], lam_g0=lam_g, lam_x0=lam_x, progress=None, on_iterate=None)
            keywords["options"] = {**keywords["options"], **WARM_START_OPTIONS, "mu_init": mu}
            clock = time.perf_counter()
            restart = nlp.solve(x, **keywords)
            print("from iteration %4d (objective %.6f), mu %.0e: %s, %d iterations, objective %.6f, %.1f s"
                  % (iteration, objective, mu, restart.status, restart.iterations, restart.objective,
                     time.perf_counter() - clock), flush=True)


if __name__ == "__main__":
    main()
