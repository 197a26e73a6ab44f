"""Experiment: how local is what limits the area modes' steps? The nonlinearity of each IPOPT step, per triangle.

    python benchmarks/step_locality.py ../shared/meshes/hand_closed.obj original-areas

For every step d of the margin stage (x -> x + d, IPOPT's own iterates), the part of the change of
the constraints (6)-(8) that the linear model misses, |g(x + d) - g(x) - J d|, is attributed to the
triangles its constraint rows touch, and the script prints how few triangles carry 90% of it (median
and quartiles over the steps). If it sat in a few spots, step control per region could let the rest
of the mesh take longer steps than one global regularisation or trust radius allows. Not part of the
package: knight.off original-areas, median 18.1% of its 1,000 triangles (quartiles 5.7-28.0%),
largest move per step median 0.26 in the log unknowns; hand_closed.obj 7.4% of 15,982 (quartiles
3.1-20.0%), largest move median 0.27: spread over many triangles, not a few spots.
"""

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from confined_shift import csc_from_casadi            # noqa: E402 (benchmarks/, beside this script)
from trust_region_probe import capture_margin_stage   # noqa: E402


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("mesh")
    parser.add_argument("mode")
    args = parser.parse_args(argv)

    iterates = {}

    def on_iterate(stage, iteration, x, lam_g, lam_x, objective):
        if stage == "margin" and iteration not in iterates:
            iterates[iteration] = np.array(x)

    _, margin = capture_margin_stage(args.mesh, args.mode, on_iterate=on_iterate, check=False)
    values, n_eq = margin["nlp"]._numeric, margin["nlp"].n_equalities
    t = values.n_faces
    rows = values._A[:n_eq].tocoo()                     # constraint rows over the triangles' h rows
    triangle_of_row = rows.col // values._width
    shares, largest = [], []
    steps = sorted(iterates)[:margin["run"].iterations + 1]
    for k in steps[:-1]:
        x, d = iterates[k], iterates[k + 1] - iterates[k]
        g = values.objective_and_constraints(x)[1][:n_eq]
        jacobian = csc_from_casadi(values.jacobian_sparsity, values.jacobian(x)[1]).tocsr()[:n_eq]
        missed = np.abs(values.objective_and_constraints(x + d)[1][:n_eq] - g - jacobian @ d)
        if not missed.sum():
            continue
        per_triangle = np.zeros(t)
        np.add.at(per_triangle, triangle_of_row, missed[rows.row])
        cumulative = np.cumsum(np.sort(per_triangle)[::-1]) / per_triangle.sum()
        shares.append((np.searchsorted(cumulative, 0.9) + 1) / t)
        largest.append(np.abs(d).max())
    shares = 100 * np.array(shares)
    print("%s %s: %d margin steps; triangles carrying 90%% of a step's missed change of (6)-(8): median "
          "%.1f%%, quartiles %.1f-%.1f%% of %d; largest move per step (log units): median %.2f, max %.2f"
          % (Path(args.mesh).name, args.mode, len(shares), np.median(shares), np.percentile(shares, 25),
             np.percentile(shares, 75), t, np.median(largest), np.max(largest)))


if __name__ == "__main__":
    main()
