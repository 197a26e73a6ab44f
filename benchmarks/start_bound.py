"""How much a better start could save an area mode: solve a mesh, then solve it again from its own
optimum (sphere positions as ``start=``), which bounds what any starting point can gain with the
current stages. With ``--no-walk`` the second solve skips the area continuation and starts the
margin stage with a small barrier (``--mu-init``), the bound for a start already at the targets.

    python benchmarks/start_bound.py ../shared/meshes/bunny.off --target original-areas [--no-walk]

Prints one JSON line per solve: iterations per stage, objective, seconds.
"""

import argparse
import json
import time

import sphere_nlp
from sphere_nlp.settings import SolverSettings


def solve(path, target, **keywords):
    began = time.perf_counter()
    result = sphere_nlp.parameterize(path, target=target, **keywords)
    return result, dict(iterations=result.iterations, objective=result.objective,
                        seconds=round(time.perf_counter() - began, 1),
                        stages=[(s["name"], s["iterations"]) for s in result.stages])


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("mesh")
    parser.add_argument("--target", default="original-areas", choices=sphere_nlp.MODES)
    parser.add_argument("--no-walk", action="store_true", help="skip the area continuation on the re-solve")
    parser.add_argument("--mu-init", type=float, default=1e-4, help="IPOPT mu_init of the re-solve with --no-walk")
    args = parser.parse_args(argv)
    direct, row = solve(args.mesh, args.target)
    print(json.dumps(dict(start="default", **row)), flush=True)
    keywords = {}
    if args.no_walk:
        # A walk of length zero: the continuation step leaves the start as it is.
        keywords = dict(settings=SolverSettings(area_continuation_iterations=0),
                        ipopt_options={"mu_init": args.mu_init})
    _, row = solve(args.mesh, args.target, start=direct.vertices[direct.vertex_map], **keywords)
    print(json.dumps(dict(start="own optimum", no_walk=args.no_walk, **row)), flush=True)


if __name__ == "__main__":
    main()
