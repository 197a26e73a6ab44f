"""Command line: ``python -m sphere_nlp INPUT [options]`` (a thin layer over :func:`parameterize`).

Exit status: 0 a certified sphere was written; 1 the solve or the certificate failed (nothing
written); 2 bad input or bad usage (nothing written).
"""

import argparse
import sys
import time
import traceback
from pathlib import Path

from . import errors
from .mesh_io import check_mesh_path
from .targets import MODES

EXAMPLES = """examples:
  python -m sphere_nlp models/cylinder.off
  python -m sphere_nlp bunny.off --target original-areas -o bunny_sphere.obj --report run.json
  python -m sphere_nlp head.ply --target equal-angles --save-solution angles.npz --quiet
  python -m sphere_nlp reproduce fig3 --out fig3/   (the paper's Fig. 3: PNG, meshes, JSON)
  python -m sphere_nlp compare a.off b.obj --out cmp/   (sphere_nlp vs. baselines: JSON, Markdown)
"""


def build_parser():
    parser = argparse.ArgumentParser(
        prog="sphere_nlp",
        description="Map a closed genus-0 triangle mesh onto the unit sphere without overlaps "
                    "(Sheffer, Gotsman & Dyn 2004), certified before it is written.",
        epilog=EXAMPLES, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("input", help="input mesh (OFF, OBJ, PLY, STL, anything trimesh reads)")
    out = parser.add_argument_group("output")
    out.add_argument("-o", "--output", help="sphere mesh to write, .off/.obj/.ply "
                                            "(default: <input stem>.sphere.off in the current folder)")
    out.add_argument("--report", metavar="R.json", help="write run statistics as JSON")
    out.add_argument("--save-solution", metavar="S.npz",
                     help="write vertices, faces, angles, excess and targets as .npz")
    method = parser.add_argument_group("method")
    method.add_argument("--target", default="original-angles", choices=MODES,
                        help="what the map aims for (default: original-angles)")
    method.add_argument("--angle-weight", type=float, help="weight of the angle term (mode default)")
    method.add_argument("--area-weight", type=float, help="weight of the area term (mode default)")
    method.add_argument("--formulation", default="log-chord", choices=("log-chord", "substituted", "faithful"),
                        help="NLP formulation (default: log-chord; faithful = the paper verbatim)")
    limits = parser.add_argument_group("solver limits")
    limits.add_argument("--max-iter", type=int, help="IPOPT iteration limit per stage")
    limits.add_argument("--max-time", type=float, help="wall-clock limit per IPOPT stage, seconds")
    misc = parser.add_argument_group("messages")
    misc.add_argument("-q", "--quiet", action="store_true", help="print only errors")
    misc.add_argument("--debug", action="store_true", help="show tracebacks")
    return parser


class Progress:
    """Progress lines on stderr: one updating line on a terminal, a line every few seconds otherwise."""

    def __init__(self, quiet=False, stream=None):
        self.stream = stream or sys.stderr
        self.quiet = quiet
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self.last = 0.0
        self.start = time.perf_counter()

    def say(self, text):
        if self.quiet:
            return
        if self.tty:
            self.stream.write("\r\033[K")
        self.stream.write(text + "\n")
        self.stream.flush()

    def iteration(self, stage, iteration, objective, violation, elapsed):
        if self.quiet:
            return
        now = time.perf_counter()
        interval = 0.2 if self.tty else 5.0
        if now - self.last < interval and iteration > 0:
            return
        self.last = now
        text = ("solve (%s): iteration %d, objective %.6g, constraint violation %.2e, %.1f s"
                % (stage, iteration, objective, violation, now - self.start))
        if self.tty:
            self.stream.write("\r\033[K" + text)
            self.stream.flush()
        else:
            self.say(text)


def run(args):
    from .api import parameterize, solve_failure_message

    input_path = Path(args.input)
    output = Path(args.output) if args.output else Path(input_path.name.split(".")[0] + ".sphere.off")
    check_mesh_path(output)
    progress = Progress(quiet=args.quiet)
    progress.say("sphere_nlp: mapping %s (target %s)" % (input_path, args.target))
    result = parameterize(str(input_path), target=args.target, angle_weight=args.angle_weight,
                          area_weight=args.area_weight, formulation=args.formulation,
                          max_iter=args.max_iter, max_time=args.max_time, progress=progress.iteration,
                          check=False)
    for repair in result.repairs:
        progress.say("repaired: " + repair)
    if args.report:
        result.write_report(args.report)
    if not result.success:
        if not result.solved:
            raise errors.SolveError(solve_failure_message(result.status, result.iterations)
                                    + "; nothing written")
        raise errors.CertificateError("the sphere failed its certificate (%s; IPOPT status %s); nothing "
                                      "written" % (result.certificate.reason, result.status))
    result.write(output)
    if args.save_solution:
        result.save_solution(args.save_solution)
    c = result.certificate
    progress.say("wrote %s: %d vertices, %s, %d iterations, %.2f s, certified (degree %.12g, 0 flipped, "
                 "norm error %.1e, constraint violation %.1e, angle error %.1e rad)"
                 % (output, len(result.vertices), result.target, result.iterations,
                    result.timings["total"], c.degree, c.max_norm_error, result.max_constraint_violation,
                    result.max_angle_error))
    return 0


def main(argv=None):
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["reproduce"]:      # `python -m sphere_nlp reproduce fig3 --out DIR`
        from .reproduce import main as reproduce_main

        return reproduce_main(argv[1:])
    if argv[:1] == ["compare"]:        # `python -m sphere_nlp compare MESH... --out DIR`
        from .compare import main as compare_main

        return compare_main(argv[1:])
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exit_:
        return int(exit_.code or 0)
    try:
        return run(args)
    except errors.SphereNLPError as exc:
        if args.debug:
            traceback.print_exc()
        print("sphere_nlp: error: %s" % exc, file=sys.stderr)
        return exc.exit_status
    except KeyboardInterrupt:
        print("sphere_nlp: interrupted; nothing written", file=sys.stderr)
        return 130
    except MemoryError:
        print("sphere_nlp: error: out of memory; nothing written", file=sys.stderr)
        return 1
    except Exception as exc:  # a bug: still one line unless --debug
        if args.debug:
            traceback.print_exc()
        print("sphere_nlp: internal error: %s: %s (rerun with --debug for a traceback)"
              % (type(exc).__name__, exc), file=sys.stderr)
        return 1
