"""Turn the end point of a ``trace_solve.py`` run into a certified sphere and a comparison row.

    python benchmarks/finish_trace.py ../shared/meshes/armadillo.obj original-areas /tmp/trace \\
        --row /tmp/trace/row.json [--sphere /tmp/trace/armadillo.sphere.off]

Reads the trace folder's last ``run<k>.npz`` (log-chord variables: log u for the 3t corners, then
log e for the t triangles) and its printed log ``trace.txt`` (the lines ``run k: STATUS, N iterations``
and the elapsed seconds of the progress lines), then does what ``parameterize`` does after its solve:
the constraint check of :func:`sphere_nlp.solve.max_constraint_violation`, the same
:func:`~sphere_nlp.api.sphere_positions` and :func:`~sphere_nlp.api.max_angle_error`,
:func:`~sphere_nlp.certify.certify`, and the distortion
measures of ``compare`` (:func:`~sphere_nlp.metrics.distortion_summary`). The row (a list of one
row, the format of ``compare.json``) can be merged into ``docs/compare.md`` with
``python benchmarks/compare_all.py --merge-from ROW.json``. Its ``valid`` is true only if the last
IPOPT run reported success, every equality holds to the solver's tolerance, no inequality is broken
and the certificate holds; the sphere is written (atomically) only then.

Exit status 0 when the row is valid, 1 when it is not (the row is written either way).
"""

import argparse
import re
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

RUN_LINE = re.compile(r"^run (\d+): (\S+), (\d+) iterations")
PROGRESS_LINE = re.compile(r"^\s*([0-9.]+) s\s")


def read_trace_log(path):
    """(statuses by run number, total iterations, last elapsed seconds) from a trace's printed log."""
    statuses, iterations, elapsed = {}, 0, 0.0
    for line in Path(path).read_text().splitlines():
        match = RUN_LINE.match(line)
        if match:
            statuses[int(match.group(1))] = match.group(2)
            iterations += int(match.group(3))
            continue
        match = PROGRESS_LINE.match(line)
        if match:
            elapsed = float(match.group(1))
    return statuses, iterations, elapsed


def main(argv=None):
    from sphere_nlp.api import max_angle_error, sphere_positions
    from sphere_nlp.certify import certify
    from sphere_nlp.mesh_io import load_mesh, write_json, write_mesh
    from sphere_nlp.metrics import distortion_summary
    from sphere_nlp.nlp import AngleNLP
    from sphere_nlp.repair import prepare_mesh
    from sphere_nlp.settings import SolverSettings
    from sphere_nlp.solve import max_constraint_violation, violates_inequalities
    from sphere_nlp.targets import make_targets

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("mesh")
    parser.add_argument("mode")
    parser.add_argument("trace", help="the --out folder of trace_solve.py, with trace.txt its printed log")
    parser.add_argument("--log", help="the printed log, if not TRACE/trace.txt")
    parser.add_argument("--row", required=True, help="write the comparison row here (JSON)")
    parser.add_argument("--sphere", help="write the certified sphere here (any format write_mesh takes)")
    args = parser.parse_args(argv)

    trace = Path(args.trace)
    runs = sorted(trace.glob("run*.npz"), key=lambda p: int(p.stem[3:]))
    if not runs:
        sys.exit("no run<k>.npz in %s" % trace)
    last = int(runs[-1].stem[3:])
    statuses, iterations, solve_s = read_trace_log(args.log or trace / "trace.txt")
    status = statuses.get(last, "unknown")

    clock = time.perf_counter()
    vertices, faces = load_mesh(args.mesh)
    prepared = prepare_mesh(vertices, faces)
    connectivity, faces = prepared.connectivity, prepared.faces
    targets = make_targets(args.mode, prepared.normalised_vertices, faces, connectivity.vertex_degree)
    angles, excess = AngleNLP(connectivity, targets).unpack(np.load(runs[-1])["x"])
    violation = max_constraint_violation(connectivity, angles, excess)
    positions, _ = sphere_positions(connectivity, angles, excess)
    certificate = certify(positions, faces)
    angle_error = max_angle_error(positions, faces, angles)
    finish_s = time.perf_counter() - clock

    solved = (status == "Solve_Succeeded" and violation <= SolverSettings().feasibility_tolerance
              and not violates_inequalities(angles, excess))
    row = {"mesh": Path(args.mesh).name, "method": "sphere_nlp:" + args.mode,
           "n_vertices": len(prepared.vertices)}
    row.update(distortion_summary(prepared.vertices, positions, faces))
    row["valid"] = bool(solved and certificate.valid)
    row.update(time_s=round(solve_s + finish_s, 4),
               status=("certified" if row["valid"] else
                       "certificate failed: " + certificate.reason if solved else
                       "not solved: last run %s, max violation %.1e" % (status, violation)),
               note="%d iterations (trace_solve.py end point, run %d)" % (iterations, last))
    write_json(args.row, [row])
    print("run %d: %s, %d iterations in all, solve %.0f s; max violation %.2e; unfold and certify %.1f s, "
          "max |angle error| %.2e rad; certificate %s; %s"
          % (last, status, iterations, solve_s, violation, finish_s, angle_error,
             "valid" if certificate.valid else certificate.reason,
             ", ".join("%s %s" % (k, row[k]) for k in ("mean_abs_angle_diff_deg", "qc_mean", "qc_max",
                                                         "mean_abs_log_area"))))
    if args.sphere and row["valid"]:
        write_mesh(args.sphere, positions, faces)
    return 0 if row["valid"] else 1


if __name__ == "__main__":
    sys.exit(main())
