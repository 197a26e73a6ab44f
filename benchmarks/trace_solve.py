"""Trace one solve stage by stage, for investigating slow or failing meshes.

    python benchmarks/trace_solve.py ../shared/meshes/nefertiti.obj original-angles --out /tmp/trace

Prints every IPOPT iteration (stage, iteration, objective, constraint violation, elapsed time), writes
IPOPT's own log (print level 5) to OUT/ipopt.log and, after every IPOPT run, OUT/run<k>.npz with its
start ``x0``, result ``x`` and multipliers ``lam_g``, ``lam_x`` (log-chord variables: log u for the 3t
corners, then log e for the t triangles), so a later stage can be studied from a saved point. With
``--checkpoint-every K`` it also saves the current iterate every K iterations to OUT/checkpoint.npz
(``x``, ``lam_g``, ``lam_x``, ``run``, ``iteration``, ``objective``), so that a run stopped before its end
(a time limit, a cap) still leaves its last point behind. ``finish_trace.py`` turns the last run into a certified sphere and a
``compare.json`` row. The area modes are traced as the NLP alone (start "conformal"), without
their authalic route (:mod:`sphere_nlp.polish`), whose polish is budgeted.
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def main(argv=None):
    from sphere_nlp.api import parameterize
    from sphere_nlp.settings import SolverSettings

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("mesh")
    parser.add_argument("mode")
    parser.add_argument("--out", required=True, help="folder for ipopt.log and run<k>.npz")
    parser.add_argument("--max-time", type=float, default=600.0, help="IPOPT limit per stage, s (600)")
    parser.add_argument("--checkpoint-every", type=int, default=0, metavar="K",
                        help="save the current iterate to OUT/checkpoint.npz every K iterations")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    runs = [0]

    def save_run(stage, nlp, run):
        runs[0] += 1
        np.savez(out / ("run%d.npz" % runs[0]), x0=run.x0, x=run.x, lam_g=run.lam_g, lam_x=run.lam_x)
        print("run %d: %s, %d iterations, objective %.10g, %.1f s"
              % (runs[0], run.status, run.iterations, run.objective, run.time_s), flush=True)

    on_iterate = None
    if args.checkpoint_every > 0:
        # the run in progress is the one after those finished (numbered as run<k>.npz)
        on_iterate = checkpoint_iterates(out / "checkpoint.npz", args.checkpoint_every, lambda: runs[0] + 1)
    start = time.perf_counter()

    def progress(stage, iteration, objective, violation, elapsed):
        print("%8.1f s  %-22s it %4d  objective %.10g  violation %.2e"
              % (time.perf_counter() - start, stage, iteration, objective, violation), flush=True)

    result = parameterize(args.mesh, args.mode, progress=progress, max_time=args.max_time, start="conformal",
                          ipopt_options={"output_file": str(out / "ipopt.log"), "file_print_level": 5},
                          settings=SolverSettings(on_run=save_run, on_iterate=on_iterate))
    print(result)
    for stage in result.stages:
        print(stage)


def checkpoint_iterates(path, every, current_run):
    """An ``on_iterate`` hook (SolverSettings) saving (x, multipliers) to ``path`` every ``every``
    iterations, labelled with ``current_run()``."""

    def save(stage, iteration, x, lam_g, lam_x, objective):
        if iteration % every == 0:
            temporary = path.with_name(path.stem + ".tmp.npz")
            np.savez(temporary, run=current_run(), iteration=iteration, objective=objective,
                     x=x, lam_g=lam_g, lam_x=lam_x)
            temporary.replace(path)

    return save


if __name__ == "__main__":
    main()
