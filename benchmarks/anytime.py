"""How good is an area-mode solve if it is stopped early? The quality of its iterates against time.

    python benchmarks/anytime.py ../shared/meshes/armadillo.obj original-areas --every 10

Runs one solve and keeps every K-th IPOPT iterate of every stage with its wall time. Afterwards it
evaluates each kept iterate with the last stage's NLP (the same constraints in every stage): the
objective (9) (the walk's stages minimise a log-area term instead, so IPOPT's own objective is not
comparable across stages), the max constraint violation, and the mean |log(e/e')| of its triangles'
excesses against the targets. A run stopped at that moment with ``--on-limit project`` is projected
onto the constraints from about there (docs/tuning.md, "projection_iterations": < 0.1% change in the
objective from violations up to 0.6), so the table says what ``--max-time`` buys. Prints one line per
kept iterate and, at the end, the first moments the area error came within 0.05 and within 10% of
the final one at violation <= 0.1. ``--markdown FILE`` appends a row to a table (benchmarks/anytime.md):
at 25%, 40%, 50% and 75% of the run's time, the latest kept iterate's objective against the final
one and its mean |log area ratio|.
"""

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def trace(mesh, mode, every=10):
    """Solve ``mesh`` in ``mode``, keeping every ``every``-th iterate of each stage and each run's end.

    Returns (result, total seconds, rows): a row per kept iterate with its ``seconds`` since the
    start, ``stage``, ``iteration``, ``objective`` (9), max constraint ``violation`` and
    ``mean_abs_log_area``, all evaluated by the last stage's NLP.
    """
    from sphere_nlp.api import parameterize
    from sphere_nlp.settings import SolverSettings

    kept, nlps = [], []
    clock = time.perf_counter()

    def on_iterate(stage, iteration, x, lam_g, lam_x, objective):
        if iteration % every == 0:
            kept.append((time.perf_counter() - clock, stage, iteration, np.array(x, float)))

    def on_run(stage, nlp, run):
        nlps.append(nlp)
        kept.append((time.perf_counter() - clock, stage, run.iterations, np.array(run.x, float)))

    # The NLP alone (start "conformal"), not the area modes' authalic route with its budgeted polish.
    result = parameterize(mesh, mode, start="conformal",
                          settings=SolverSettings(on_iterate=on_iterate, on_run=on_run))
    total = time.perf_counter() - clock
    values = nlps[-1]._numeric
    t = len(result.target_excess)
    log_target = np.log(result.target_excess)
    rows = []
    for elapsed, stage, iteration, x in kept:
        f, g = values.objective_and_constraints(x)
        rows.append(dict(seconds=elapsed, stage=stage, iteration=iteration, objective=float(f),
                         violation=float(np.abs(g).max()),
                         mean_abs_log_area=float(np.abs(x[3 * t:] - log_target).mean())))
    return result, total, rows


def markdown_row(mesh, mode, result, total, rows, fractions=(0.25, 0.4, 0.5, 0.75)):
    """The row of benchmarks/anytime.md: at each fraction of the run's time, the latest kept iterate's
    objective against the final one (per cent above it, or a factor beyond 2) and its mean |log area
    ratio| (empty before the first kept iterate)."""
    cells = []
    for fraction in fractions:
        before = [r for r in rows if r["seconds"] <= fraction * total]
        if not before:
            cells.append("")
            continue
        ratio = before[-1]["objective"] / result.objective
        cells.append("%s / %.3f" % ("%.0f x" % ratio if ratio > 2 else "%+.1f%%" % (100 * (ratio - 1)),
                                    before[-1]["mean_abs_log_area"]))
    return "| %s | %s | %.0f | %d | %.6g | %.3f | %s |" % (
        Path(mesh).name, mode, total, result.iterations, result.objective, rows[-1]["mean_abs_log_area"],
        " | ".join(cells))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("mesh")
    parser.add_argument("mode")
    parser.add_argument("--every", type=int, default=10, help="keep every K-th iterate of each stage (10)")
    parser.add_argument("--out", help="write the kept iterates' figures to this JSON file")
    parser.add_argument("--markdown", help="append a summary row to this markdown table")
    args = parser.parse_args(argv)

    result, total, rows = trace(args.mesh, args.mode, args.every)
    print("%s %s: %s, success %s, %d iterations, objective %.6f, %.1f s"
          % (Path(args.mesh).name, args.mode, result.status, result.success, result.iterations,
             result.objective, total))
    for row in rows:
        print("%(seconds)8.1f s  %(stage)-28s %(iteration)5d  objective %(objective)12.4f  "
              "violation %(violation).1e  mean |log area ratio| %(mean_abs_log_area).4f" % row)
    final = rows[-1]["mean_abs_log_area"]
    for label, bound in (("0.05", 0.05), ("1.1 x final", 1.1 * final)):
        first = next((r for r in rows if r["violation"] <= 0.1 and r["mean_abs_log_area"] <= bound), None)
        print("mean |log area ratio| <= %s (%.4f) at violation <= 0.1: %s" % (
            label, bound, "%.1f s (%.0f%% of the run), %s iteration %d, objective %.4f" % (
                first["seconds"], 100 * first["seconds"] / total, first["stage"], first["iteration"],
                first["objective"]) if first else "never"))
    if args.markdown:
        with open(args.markdown, "a") as table:
            table.write(markdown_row(args.mesh, args.mode, result, total, rows) + "\n")
    if args.out:
        Path(args.out).write_text(json.dumps(dict(mesh=Path(args.mesh).name, mode=args.mode, total_s=total,
                                                  objective=result.objective, rows=rows), indent=1))


if __name__ == "__main__":
    main()
