"""Trace one solve stage by stage, for investigating slow or failing meshes.

    python benchmarks/trace_solve.py ../shared/meshes/nefertiti.obj original-angles --out /tmp/trace

Prints every IPOPT iteration (stage, iteration, objective, constraint violation, elapsed time), writes
IPOPT's own log (print level 5) to OUT/ipopt.log and, after every IPOPT run, OUT/run<k>.npz with its
start ``x0``, result ``x`` and multipliers ``lam_g``, ``lam_x`` (log-chord variables: log u for the 3t
corners, then log e for the t triangles), so a later stage can be studied from a saved point. With
``--checkpoint-every K`` it also saves the current iterate every K iterations to OUT/checkpoint.npz
(``x``, ``lam_g``, ``lam_x``, ``run``, ``iteration``, ``objective``), so that a run stopped before its end
(a session's time limit, a cap) still leaves its last point behind. ``finish_trace.py`` turns the last run into a certified sphere and a
``compare.json`` row.
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def main(argv=None):
    import sphere_nlp.nlp as nlp_module
    from sphere_nlp.api import parameterize

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
    original_solve = nlp_module.AngleNLP.solve
    runs = [0]
    if args.checkpoint_every > 0:
        # the run in progress is the one after those finished (numbered as run<k>.npz)
        checkpoint_iterates(out / "checkpoint.npz", args.checkpoint_every, nlp_module, lambda: runs[0] + 1)

    def saving_solve(self, x0, *pos, **kw):
        run = original_solve(self, x0, *pos, **kw)
        runs[0] += 1
        np.savez(out / ("run%d.npz" % runs[0]), x0=x0, x=run["x"], lam_g=run["lam_g"], lam_x=run["lam_x"])
        print("run %d: %s, %d iterations, objective %.10g, %.1f s"
              % (runs[0], run["status"], run["iterations"], run["objective"], run["time_s"]), flush=True)
        return run

    nlp_module.AngleNLP.solve = saving_solve
    start = time.perf_counter()

    def progress(stage, iteration, objective, violation, elapsed):
        print("%8.1f s  %-22s it %4d  objective %.10g  violation %.2e"
              % (time.perf_counter() - start, stage, iteration, objective, violation), flush=True)

    result = parameterize(args.mesh, args.mode, progress=progress, max_time=args.max_time,
                          ipopt_options={"output_file": str(out / "ipopt.log"), "file_print_level": 5})
    print(result)
    for stage in result.stages:
        print(stage)


def checkpoint_iterates(path, every, nlp_module, current_run):
    """Make IPOPT's iteration callback save (x, multipliers) to ``path`` every ``every`` iterations,
    labelled with ``current_run()``."""
    import casadi as ca

    names = ca.nlpsol_out()
    original_eval = nlp_module._ProgressCallback.eval

    def saving_eval(self, arg):
        if self.iteration % every == 0:
            values = {name: np.asarray(arg[names.index(name)]).ravel() for name in ("x", "lam_g", "lam_x")}
            temporary = path.with_name(path.stem + ".tmp.npz")
            np.savez(temporary, run=current_run(), iteration=self.iteration,
                     objective=float(arg[names.index("f")]), **values)
            temporary.replace(path)
        return original_eval(self, arg)

    nlp_module._ProgressCallback.eval = saving_eval


if __name__ == "__main__":
    main()
