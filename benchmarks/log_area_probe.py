"""Experiment: would a convex area term shorten the area modes? The walk's last step solved to the end.

    python benchmarks/log_area_probe.py ../shared/meshes/bunny.off original-areas

The walk (``sphere_nlp.solve.area_continuation``) ends with a step whose area term is
sum (log e - log e')^2 at the final targets, convex in the log unknowns, capped at a few iterations;
the margin stage then solves (9) from there. This script runs the usual solve, then solves that last
step's NLP (the same bounds and options, warm-started) to convergence from where the walk left it,
and prints its iterations, its (9) objective, violation and mean |log area ratio| beside the default
path's. Not part of the package: knight.off original-areas 24 more iterations (the margin stage of
(9): 71), (9) objective 24.35 against 21.05; bunny.off 75 (62), 39.08 against 33.90 (docs/design.md,
"Where the area modes' iterations go").
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from trust_region_probe import capture_stages     # noqa: E402 (benchmarks/, beside this script)


def main(argv=None):
    from sphere_nlp.settings import WARM_START_OPTIONS

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("mesh")
    parser.add_argument("mode")
    args = parser.parse_args(argv)

    clock = time.perf_counter()
    result, stages = capture_stages(args.mesh, args.mode, ("area-continuation-1", "margin"), check=False)
    total = time.perf_counter() - clock
    t = len(result.target_excess)
    log_target = np.log(result.target_excess)
    walk = [s for s in result.stages if s["name"].startswith("area-continuation")]
    print("default path: %d iterations (walk %d, margin stage %d), %.1f s, objective %.4f, "
          "mean |log area ratio| %.4f" % (
              result.iterations, sum(s["iterations"] for s in walk), stages["margin"]["run"].iterations, total,
              result.objective, np.abs(np.log(result.excess) - log_target).mean()))
    margin_values = stages["margin"]["nlp"]._numeric

    def figures(x):
        f, g = margin_values.objective_and_constraints(x)
        return f, np.abs(g).max(), np.abs(x[3 * t:] - log_target).mean()

    nlp, run, keywords = (stages["area-continuation-1"][key] for key in ("nlp", "run", "keywords"))
    print("walk's end: (9) objective %.4f, violation %.1e, mean |log area ratio| %.4f" % figures(run.x))
    options = dict(keywords["options"], **WARM_START_OPTIONS)
    options.update(max_iter=3000, mu_init=1e-4)
    keywords = dict(keywords, lam_g0=run.lam_g, lam_x0=run.lam_x, progress=None, on_iterate=None, options=options)
    clock = time.perf_counter()
    finished = nlp.solve(run.x, **keywords)
    print("walk's last step solved on: %s, %d more iterations, %.1f s; (9) objective %.4f, violation %.1e, "
          "mean |log area ratio| %.4f" % ((finished.status, finished.iterations, time.perf_counter() - clock)
                                         + figures(finished.x)))


if __name__ == "__main__":
    main()
