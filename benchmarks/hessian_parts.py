"""Where a log-chord solve's negative curvature comes from: the Lagrangian Hessian split by term.

    python benchmarks/hessian_parts.py ../shared/meshes/bunny.off equal-areas /tmp/trace

Reads the last ``run<k>.npz`` of a ``trace_solve.py`` folder (its point ``x``, multipliers ``lam_g``
and start ``x0``) and evaluates the per-triangle 4x4 blocks of the Lagrangian's Hessian at ``x`` for
the objective alone and for each constraint family alone ((6) triangle sums, (7) vertex sums, (8)
edges) with that run's multipliers, then prints each part's smallest block eigenvalue, how many blocks
are indefinite and the sum of the negative eigenvalues. IPOPT regularises the whole KKT matrix when its
inertia is wrong, so a part whose negative curvature dominates is the one to reformulate.

The NLP is rebuilt as ``solve_angles`` builds its last stage (the three left-out vertices of the
start, corners obtuse at the run's start flagged), so the blocks are that stage's.
"""

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def main(argv=None):
    from sphere_nlp import solve, starts
    from sphere_nlp.settings import SolverSettings
    from sphere_nlp.mesh_io import load_mesh
    from sphere_nlp.nlp import AngleNLP
    from sphere_nlp.repair import prepare_mesh
    from sphere_nlp.targets import make_targets

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("mesh")
    parser.add_argument("mode")
    parser.add_argument("trace", help="a trace_solve.py --out folder")
    args = parser.parse_args(argv)

    vertices, faces = load_mesh(args.mesh)
    prepared = prepare_mesh(vertices, faces)
    connectivity = prepared.connectivity
    targets = make_targets(args.mode, prepared.normalised_vertices, prepared.faces, connectivity.vertex_degree)
    runs = sorted(Path(args.trace).glob("run*.npz"), key=lambda p: int(p.stem[3:]))
    run = np.load(runs[-1])
    x, lam_g = run["x"], run["lam_g"]
    t = connectivity.n_faces
    gauge = SolverSettings().start_gauge if targets.area_weight == 0 else "area"
    _, _, start_positions, _ = starts.feasible_start(connectivity, prepared.normalised_vertices, gauge=gauge)
    dropped = solve.independent_vertices(start_positions)
    obtuse = AngleNLP(connectivity, targets).unpack(run["x0"])[0] > SolverSettings().obtuse_angle
    nlp = AngleNLP(connectivity, targets, dropped_vertices=dropped, obtuse_corners=obtuse)
    values, upper = nlp._numeric, nlp._parts["upper"]          # blocks in _log_chord_parts' order
    n_kept = connectivity.n_vertices - len(dropped)
    families = {"(6)": slice(0, t), "(7)": slice(t, t + n_kept), "(8)": slice(t + n_kept, None)}

    def blocks(lam_f, multipliers):
        entries = values.hessian(x, lam_f, multipliers)
        B = np.zeros((t, 4, 4))
        for k, (i, j) in enumerate(upper):
            B[:, i, j] = B[:, j, i] = entries[values._block_positions[k]]
        return B

    for name, part in families.items():
        print("%s multipliers: median |lambda| %.3g, max %.3g"
              % (name, np.median(np.abs(lam_g[part])), np.abs(lam_g[part]).max()))
    parts = {"objective": blocks(1.0, np.zeros_like(lam_g))}
    for name, part in families.items():
        masked = np.zeros_like(lam_g)
        masked[part] = lam_g[part]
        parts[name] = blocks(0.0, masked)
    parts["total"] = blocks(1.0, lam_g)
    for name, B in parts.items():
        eigenvalues = np.linalg.eigvalsh(B)
        print("%-10s min eigenvalue %9.3g; indefinite blocks %6d of %d; sum of negative eigenvalues %.3g"
              % (name, eigenvalues.min(), np.sum(eigenvalues.min(1) < -1e-3), t,
                 eigenvalues[eigenvalues < 0].sum()))


if __name__ == "__main__":
    main()
