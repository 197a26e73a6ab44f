"""Command line: ``sphere-nlp INPUT [options]`` (a thin layer over :func:`parameterize`) and
``sphere-nlp COMMAND ...`` for the subcommands of :data:`sphere_nlp.commands.SUBCOMMANDS`.

Exit status: 0 a certified sphere was written; 1 the solve or the certificate failed (nothing
written but ``--report``); 2 bad input or bad usage, found before any solving (nothing written);
130 / 143 ended by SIGINT / SIGTERM at any moment, start-up included (nothing written or replaced).
All outputs of a run are renamed into place together, only after everything succeeded
(:func:`sphere_nlp.mesh_io.output_transaction`).

Only light modules are imported here: the console script imports this module before :func:`main`
takes over the signals (:func:`sphere_nlp.interrupts.program_started`), so numpy, CasADi and
trimesh load afterwards.
"""

import argparse
import math
import os
import signal
import sys
import time
import traceback
from pathlib import Path

from . import __version__, errors, interrupts
from .commands import (PROG, SUBCOMMANDS, UP_CHOICES, SafeStream, UsageParser, check_output_paths as _check_paths,
                       join_negative_values, subcommand_lines, subcommand_main, unknown_command, view_argument,
                       warnings_silenced)

# SolverSettings' area_floor, repeated so that --help need not import numpy (tests/test_ux.py
# checks that the two agree).
DEFAULT_AREA_FLOOR = 1e-12

# Three runnable examples (tests/test_ux.py runs each of them).
EXAMPLES = """examples:
  sphere-nlp models/cylinder.off
  sphere-nlp models/cylinder.off -o cylinder.obj --png
  sphere-nlp models/cylinder.off --target equal-areas --textured-input painted.obj --report run.json
"""


def build_parser():
    from .names import CORNER_WEIGHTINGS, FORMULATIONS, MODES, ON_LIMIT

    parser = UsageParser(
        prog=PROG,
        usage="%(prog)s INPUT [options]\n       %(prog)s COMMAND ... (see below; COMMAND --help for each)",
        description="Map a closed genus-0 triangle mesh onto the unit sphere without overlaps\n"
                    "(Sheffer, Gotsman & Dyn 2004), certified before anything is written.\n\n"
                    "commands:\n" + subcommand_lines(),
        epilog=EXAMPLES, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("input", help="input mesh: OFF, OBJ, PLY, STL, FreeSurfer (lh.pial), GIFTI (.gii), "
                                      "anything trimesh reads; polygons are split into triangles")
    parser.add_argument("--version", action="version", version="sphere-nlp " + __version__)
    out = parser.add_argument_group("output (each written atomically, only for a certified sphere)")
    out.add_argument("-o", "--output", metavar="OUT", help="sphere mesh, .off/.obj/.ply/.glb/.gltf; .obj carries "
                                            "longitude/latitude texture coordinates (default: <input name "
                                            "without its last extension>[.MODE unless the default]"
                                            ".sphere.off here)")
    out.add_argument("--png", action="store_true",
                     help="picture beside the sphere, named after it (-o cyl.obj: cyl.png; bunny.sphere.off: "
                          "bunny.png), as in batch: mesh and sphere coloured by distortion, mesh checkerboarded; "
                          "'%s picture MESH SPHERE' redraws it later without solving" % PROG)
    out.add_argument("--png-measure", choices=("area", "angle"),
                     help="colouring of the picture: log area ratio or angle distortion (default: the "
                          "one the target mode does not optimise)")
    out.add_argument("--view", metavar="AZ,EL", type=view_argument,
                     help="camera azimuth and elevation of the picture, degrees, e.g. --view -60,20 "
                          "(default: the side with the most projected area)")
    out.add_argument("--up", choices=UP_CHOICES, metavar="AXIS",
                     help="the input's up axis in the picture: x, y, z, or --up=-z (default: detected)")
    out.add_argument("--textured-input", metavar="OUT.obj",
                     help="the input mesh with the sphere's texture coordinates, to paint or texture")
    out.add_argument("--texture", metavar="NAME.png",
                     help="with an OBJ output: write a checkerboard texture NAME.png and an .mtl beside "
                          "each OBJ, referenced by it, so viewers show the map")
    out.add_argument("--report", metavar="R.json", help="run statistics as JSON (also on failure)")
    out.add_argument("--save-solution", metavar="S.npz",
                     help="vertices, faces, angles, excess and targets as .npz")
    out.add_argument("--save-distortion", metavar="D.npz",
                     help="distortion per face and per vertex as .npz: log area ratio, angle distortion, "
                          "quasi-conformal ratio (to colour the mesh or find where the map pays)")
    method = parser.add_argument_group("method")
    method.add_argument("--target", default="original-angles", choices=MODES, metavar="MODE",
                        help="what the map aims for: %s (default: original-angles)" % ", ".join(MODES))
    method.add_argument("--angle-weight", type=float, metavar="W", help="weight of the angle term")
    method.add_argument("--area-weight", type=float, metavar="W", help="weight of the area term")
    method.add_argument("--formulation", default="log-chord", choices=FORMULATIONS, metavar="F",
                        help="log-chord (default), substituted or faithful (the paper verbatim)")
    method.add_argument("--corner-weighting", choices=CORNER_WEIGHTINGS, default=None,
                        help="angle term: relative errors, weights 1/beta^2 (default in the angle modes), "
                             "or uniform (the paper's (9) verbatim; default in the area modes)")
    method.add_argument("--corner-floor", type=float, metavar="F",
                        help="a floor is a lower bound the map keeps, so that no triangle collapses: every "
                             "spherical corner >= F x its target angle (default 0.1; 0 in the area modes), and "
                             "in the angle modes every corner whose target is below 10 degrees >= half of it "
                             "(0: no corner floor at all)")
    method.add_argument("--area-floor", type=float, metavar="F",
                        help="every spherical triangle >= F x the mean area 4 pi / t (default %g; 0: off)"
                             % DEFAULT_AREA_FLOOR)
    method.add_argument("--start", metavar="SPHERE",
                        help="start from an earlier sphere of this mesh (one sphere-nlp wrote for it, or for "
                             "a mesh with the same triangles); near the targets the area modes then skip "
                             "their walk, and solving a map again takes a few iterations. 'conformal': the "
                             "area modes' NLP alone from the conformal map, without the authalic stage "
                             "(slow on large meshes; ./conformal for a file of that name)")
    limits = parser.add_argument_group("solver limits (reaching one is a failure, unless --on-limit project)")
    limits.add_argument("--max-iter", type=int, metavar="N", help="IPOPT iteration limit per stage (>= 1)")
    limits.add_argument("--max-time", type=_seconds, metavar="S",
                        help="wall-clock limit of the whole run from the start of the process, seconds (> 0; "
                             "the start map is cut short and IPOPT stops at its first iteration past it). "
                             "The area modes have a budget by default (1.3 ms a vertex, at least 5 s) for "
                             "their authalic map and its polish; 'none' lets the polish run to IPOPT's optimum")
    limits.add_argument("--on-limit", choices=ON_LIMIT, default="fail",
                        help="when the main stage reaches a limit: fail (default), or project its last "
                             "iterate onto the constraints and write that certified, not optimal, sphere")
    misc = parser.add_argument_group("messages")
    misc.add_argument("-q", "--quiet", action="store_true", help="print only errors")
    misc.add_argument("--debug", action="store_true", help="show tracebacks")
    return parser


# A solve stage running this long without a time limit gets one note on how to bound it: the area
# modes' NLP run to its optimum (--max-time none) takes 15-35 minutes at 43k-50k vertices and had not
# converged after 2.5 hours at 173k (README, Sizes and speed).
LONG_STAGE_S = 600.0
# The figure is benchmarks/anytime.md's: at half of its time an area-mode run is within about 3% of
# the optimum's objective and has its area error.
LONG_STAGE_NOTE = ("sphere-nlp: note: this IPOPT stage has run for %s (large meshes in the area modes "
                   "can take hours); to bound a run, start it with --max-time SECONDS --on-limit project, which "
                   "writes a certified, not optimal, sphere when a stage reaches the limit (an area-mode run stopped "
                   "halfway ends within about 3%% of the optimum's objective)")


class Progress:
    """Progress on stderr: one updating line on a terminal, plain lines otherwise; nothing when quiet.

    The updating line shows the stage (load, build, solve, unfold, certify, write), and while solving
    IPOPT's iteration, objective and constraint violation; all with the elapsed time. Any other
    message first ends that line with a newline, so nothing is written over it. With
    ``long_stage_s``, the first IPOPT stage to run that long adds :data:`LONG_STAGE_NOTE`, once.
    """

    def __init__(self, quiet=False, stream=None, long_stage_s=None):
        self.stream = stream or sys.stderr
        self.quiet = quiet
        self.long_stage_s = long_stage_s
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self.start = time.perf_counter()
        # When the progress state was last shown: a log gets its first state line after a pause,
        # not "load, 0.0 s" ahead of an input error.
        self.last = self.start
        self.pending = False            # an unfinished updating line is on the terminal

    def elapsed(self):
        return time.perf_counter() - self.start

    def finish_line(self):
        """End the updating line (if any) so the next message starts on a line of its own."""
        if self.pending:
            self.stream.write("\n")
            self.stream.flush()
            self.pending = False

    def clear_line(self):
        """Erase the updating line (if any): an error message then stands alone."""
        if self.pending:
            self.stream.write("\r\033[K")
            self.stream.flush()
            self.pending = False

    def say(self, text):
        if self.quiet:
            return
        self.finish_line()
        self.stream.write(text + "\n")
        self.stream.flush()
        self.last = time.perf_counter()

    def _update(self, text, always=False):
        """Show a progress state: rewrite the terminal line, or log a line every few seconds."""
        now = time.perf_counter()
        # A terminal line can change often; a log file gets a line every 2 s of a running stage.
        interval = 0.2 if self.tty else 2.0
        if now - self.last < interval and not always:
            return
        self.last = now
        if self.tty:
            self.stream.write("\r\033[K" + text)
            self.stream.flush()
            self.pending = True
        else:
            self.say(text)

    def stage(self, name):
        if not self.quiet:
            # Stages are always shown on a terminal; in a log only when they start after a pause.
            self._update("%s, %.1f s" % (name, self.elapsed()), always=self.tty)

    def iteration(self, stage, iteration, objective, violation, elapsed):
        if self.long_stage_s is not None and elapsed >= self.long_stage_s:
            limit = self.long_stage_s
            self.say(LONG_STAGE_NOTE % ("%.0f minutes" % (limit / 60) if limit >= 120 else "%.0f s" % limit))
            self.long_stage_s = None
        if self.quiet:
            return
        if stage.startswith("start (untangle)"):
            # The start's repair of a conformal map: its steps, no objective yet.
            self._update("%s: step %d, %d flipped triangles in this round, %.1f s"
                         % (stage, iteration, objective, self.elapsed()))
        elif stage.startswith("start"):
            self._update("%s, %.1f s" % (stage, self.elapsed()))
        elif stage.startswith("authalic"):
            # The area modes' first-order stage (SEM's solves, then the descent's steps): its
            # energy, no constraints (every iterate is a certified map).
            self._update("%s: step %d, area energy %.6g, %.1f s" % (stage, iteration, objective, self.elapsed()))
        else:
            self._update("solve (%s): iteration %d, objective %.6g, constraint violation %.2e, %.1f s"
                         % (stage, iteration, objective, violation, self.elapsed()),
                         always=self.tty and iteration == 0)


def summary_line(output, result):
    """The run in one line: vertices, mode, time, certificate and mean distortion."""
    c = result.certificate
    d = result.distortion()
    line = ("wrote %s: %d vertices, %s, %.2f s, certified (degree %.12g, 0 flipped), mean angle "
            "distortion %.2f°, mean |log area ratio| %.3f"
            % (output, len(result.vertices), result.target, result.timings["total"], c.degree,
               d["mean_abs_angle_diff_deg"], d["mean_abs_log_area"]))
    if result.area_route is not None:
        from .polish import describe
        line += "; " + describe(result.area_route)
    elif not result.converged:
        cap = next((stage["iteration_cap"] for stage in result.stages if stage.get("iteration_cap")), None)
        limit = ("its iteration cap for a mesh of this size (%d a stage; --max-iter sets another)" % cap
                 if cap else "its limit")
        line += ("; NOT OPTIMAL: the solve reached %s after %d iterations (IPOPT %s), and the map it "
                 "had reached was made valid and certified, not finished" % (limit, result.iterations, result.status))
    return line


def floor_note(result, corner_floor, area_floor=None):
    """A line on the floors after a certified run, or None: how many corners and triangles the map
    would have made smaller than the floors allow (``corner_floor``, ``area_floor``: the values
    given, None for the defaults), or, in an area mode run without a corner floor, how many corners
    collapsed below 0.1 x their target and how to keep them."""
    area_mode = result.target.endswith("-areas")
    collapsed = result.usability()["corners_below_fraction"] if area_mode and not corner_floor else 0
    if collapsed:
        return ("%d of %d corners ended below 0.1 x their target angle: reaching the areas shears "
                "their triangles; --corner-floor 0.1 keeps them, at a cost in area error (docs/tuning.md)"
                % (collapsed, result.angles.size))
    parts = []
    if result.floor_corners and (corner_floor or not area_mode):
        parts.append("%d corners at their smallest allowed angle (%s: --corner-floor)"
                     % (result.floor_corners, "%g x their target" % corner_floor if corner_floor else
                        "0.1 x their target, half of it below 10 degrees"))
    if result.floor_triangles:
        parts.append("%d triangles at their smallest allowed area (%g x the mean: --area-floor)"
                     % (result.floor_triangles, area_floor if area_floor is not None else DEFAULT_AREA_FLOOR))
    if not parts:
        return None
    return ("the map held " + " and ".join(parts) + ", where it would have made them smaller (a floor is a "
            "lower bound that keeps triangles usable)")


def _check_suffix(path, suffix, what):
    if path and Path(path).suffix.lower() != suffix:
        raise errors.UsageError("cannot write %s: %s must end in %s" % (path, what, suffix))


def _texture_beside(obj_path, texture):
    """Where --texture goes for an OBJ: a bare file name beside the OBJ, a path as given."""
    if not texture:
        return None
    texture = Path(texture)
    return Path(obj_path).parent / texture if texture.parent == Path(".") else texture


def default_output(input_path, target="original-angles"):
    """``<input name without its last extension>.sphere.off``, in the current folder; a mode other
    than the default is named in it (``bunny.original-areas.sphere.off``), so that an area-mode run
    does not replace the default run's sphere as if it were the same map.

    ``knight.v1.off`` gives ``knight.v1.sphere.off`` (not ``knight.sphere.off``, which ``knight.v2.off``
    would overwrite), ``.hidden.off`` gives ``.hidden.sphere.off``.
    """
    mode = "" if target == "original-angles" else "." + target
    return Path(Path(input_path).stem + mode + ".sphere.off")


def check_output_paths(input_path, outputs):
    """Raise UsageError unless every output can be written, before anything is solved
    (:func:`sphere_nlp.commands.check_output_paths` with the input mesh as the one input)."""
    _check_paths([("the input file", input_path)], outputs)


def _seconds(text):
    """--max-time: seconds, or the word 'none' (no limit, kept as the string)."""
    if text.strip().lower() == "none":
        return "none"
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError("expected seconds or 'none', not %r" % text) from None


def _max_time(args):
    """--max-time for :func:`parameterize`: seconds, math.inf for 'none', or None (the default)."""
    return math.inf if args.max_time == "none" else args.max_time


def _time_limit(args):
    """--max-time as a limit on the run: seconds, or None for none given and for 'none'."""
    return None if args.max_time == "none" else args.max_time


def check_arguments(args):
    """Option values the parser cannot check itself (UsageError), before the mesh is read."""
    from .api import _check_arguments

    seconds = _time_limit(args)
    for option, value in (("--max-time", seconds), ("--angle-weight", args.angle_weight),
                          ("--area-weight", args.area_weight)):
        if value is not None and not math.isfinite(value):
            raise errors.UsageError("%s must be a finite number, not %s" % (option, value))
    if seconds is not None and seconds <= 0:
        raise errors.UsageError("--max-time must be > 0 seconds, not %g" % seconds)
    if args.max_iter is not None and args.max_iter <= 0:
        raise errors.UsageError("--max-iter must be >= 1, not %d" % args.max_iter)
    for option, value in (("--corner-floor", args.corner_floor), ("--area-floor", args.area_floor)):
        if value is not None and not 0 <= value < 1:            # NaN fails too
            raise errors.UsageError("%s must be a number in [0, 1) (0: no floor), not %s" % (option, value))
    try:
        _check_arguments(angle_weight=args.angle_weight, area_weight=args.area_weight,
                         max_iter=args.max_iter, max_time=seconds, ipopt_options=None)
    except errors.UsageError as exc:           # the API's words for the options' values
        raise errors.UsageError(str(exc).replace("angle_weight", "--angle-weight")
                                .replace("area_weight", "--area-weight").replace("max_iter", "--max-iter")
                                .replace("max_time", "--max-time")) from None


def failure_line(result, report=None):
    """The line of a run that wrote no sphere: why, what IPOPT's iteration count counts, and what
    was written (nothing, or only the report)."""
    from .nlp import status_kind

    stages = result.stages or []

    def iterations(n):
        return "%d iteration%s" % (n, "" if n == 1 else "s")

    if len(stages) > 1:
        count = ("IPOPT status %s in stage %s after %s; %s over %d stages in all, --max-iter limits each "
                 "stage" % (result.status, stages[-1]["name"], iterations(stages[-1]["iterations"]),
                            iterations(result.iterations), len(stages)))
    else:
        count = "IPOPT status %s after %s" % (result.status, iterations(result.iterations))
    if result.status == "Maximum_WallTime_Exceeded" and result.iterations == 0:
        count += "; the time limit was reached before IPOPT's first iteration"
    route = result.area_route or {}
    if route.get("answer") == "none":
        why = route["reason"]
    elif not result.solved:
        if status_kind(result.status) == "solved":
            # IPOPT converged, but to angles that break a constraint of (3)-(8).
            why = ("the angle solve ended outside the constraints: a zero or negative angle or excess, or "
                   "an equality residual above 1e-8 (%s)" % count)
        else:
            why = "the angle solve failed (%s)" % count
    else:
        why = "the sphere failed its certificate (%s; %s)" % (result.certificate.reason, count)
    return why + ("; nothing written but the report %s" % report if report else "; nothing written")


def picture_name(sphere_path):
    """Where --png writes: :func:`sphere_nlp.picture.picture_name` (repeated here so that --help
    need not import numpy; a doctest keeps the two alike).

    >>> from sphere_nlp import picture
    >>> all(picture_name(p) == picture.picture_name(p) for p in ("a/b.sphere.off", "c.obj", "d.x.sphere.ply"))
    True
    """
    path = Path(sphere_path)
    stem = path.stem[:-len(".sphere")] if path.stem.endswith(".sphere") else path.stem
    return path.with_name((stem or path.stem) + ".png")


def png_given_a_name(argv):
    """A UsageError for ``--png NAME.png`` (--png takes no name: the picture goes beside the sphere),
    or None; argparse would only call the name an unrecognized argument."""
    for option, value in zip(argv, argv[1:]):
        if option == "--png" and value.lower().endswith(".png"):
            return errors.UsageError("--png takes no file name: the picture goes beside the sphere, named after "
                                     "it (for %s, give the sphere that name: -o %s)"
                                     % (value, Path(value).with_suffix(".off")))
    return None


def run(args, progress):
    from .api import parameterize
    from .mesh_io import check_mesh_path, load_mesh, output_transaction

    input_path = Path(args.input)
    output = Path(args.output) if args.output else default_output(input_path, args.target)
    # Every option and output path is checked before the (possibly long) solve.
    check_arguments(args)
    check_mesh_path(output)
    _check_suffix(args.textured_input, ".obj", "a textured mesh")
    _check_suffix(args.texture, ".png", "a texture")
    _check_suffix(args.save_distortion, ".npz", "a distortion file")
    is_obj = output.suffix.lower() == ".obj"
    if args.texture and not is_obj and not args.textured_input:
        raise errors.UsageError("--texture needs an OBJ output (-o X.obj or --textured-input X.obj)")
    outputs = [("-o" if args.output else "the default output", output)]
    png = picture_name(output) if args.png else None
    outputs += [(option, Path(path)) for option, path in
                (("--png", png), ("--textured-input", args.textured_input),
                 ("--save-solution", args.save_solution), ("--save-distortion", args.save_distortion),
                 ("--report", args.report)) if path]
    # The texture image goes beside each OBJ written (one file when both OBJs share a folder).
    textures = {_texture_beside(obj, args.texture).resolve() for obj in
                ([output] if is_obj else []) + ([Path(args.textured_input)] if args.textured_input else [])
                if args.texture}
    outputs += [("--texture", path) for path in sorted(textures)]
    _check_paths([("the input file", input_path), ("the --start sphere", args.start)], outputs)

    def on_stage(name):
        interrupts.raise_if_interrupted()      # a signal a library caught ends the run here
        # Announced once the mesh has been read and validated, so bad input gets only its error line.
        if name == "solve":
            progress.say("sphere-nlp: mapping %s (target %s)" % (input_path, args.target))
        progress.stage(name)

    start = None
    if args.start == "conformal":
        start = "conformal"
    elif args.start:
        # Read here; parameterize checks it against the mesh before the solve is announced.
        try:
            start, _ = load_mesh(args.start)
        except errors.MeshInputError as exc:
            raise errors.UsageError("--start: %s" % exc) from None
    # --max-time counts from the start of the process: imports, reading and the start map included.
    seconds = _time_limit(args)
    remaining = None if seconds is None else seconds - interrupts.program_elapsed()
    with interrupts.deadline(remaining):
        result = parameterize(str(input_path), target=args.target, angle_weight=args.angle_weight,
                              area_weight=args.area_weight, formulation=args.formulation,
                              corner_weighting=args.corner_weighting, corner_floor=args.corner_floor,
                              area_floor=args.area_floor,
                              max_iter=args.max_iter, max_time=_max_time(args), on_limit=args.on_limit,
                              progress=progress.iteration,
                              on_stage=on_stage, start=start, check=False)
    for repair in result.repairs:
        progress.say("repaired: " + repair)
    if not result.success:
        if args.report:
            with output_transaction():
                result.write_report(args.report)
        error = errors.SolveError if not result.solved else errors.CertificateError
        raise error(failure_line(result, args.report))
    progress.stage("write")
    _write_hook("start")
    # All outputs are staged as temporary files and renamed into place together at the end.
    with output_transaction():
        result.write(output, texture=_texture_beside(output, args.texture) if is_obj else None)
        if args.textured_input:
            result.write_textured_input(args.textured_input,
                                        texture=_texture_beside(args.textured_input, args.texture))
        if args.save_solution:
            result.save_solution(args.save_solution)
        if args.save_distortion:
            result.save_distortion(args.save_distortion)
        if args.png:
            progress.stage("write (picture)")
            result.write_png(png, measure=args.png_measure, view=args.view, up=args.up)
        if args.report:
            result.write_report(args.report)
        _write_hook("staged")
    # Committed (interrupts.committed): from here on a signal no longer undoes the run.
    progress.say(summary_line(output, result))
    note = floor_note(result, args.corner_floor, args.area_floor)
    if note:
        progress.say(note)
    shrunk = result.shrinkage()["note"]
    if shrunk:
        progress.say(shrunk)
    return 0


def _write_hook(moment):
    """Test-only pause while writing: with SPHERE_NLP_TEST_WRITE_PAUSE set to "<moment>:<seconds>",
    sleep there ("start": before any output, "staged": all temporary files written, none renamed),
    so that a test can send a signal at that moment."""
    spec = os.environ.get("SPHERE_NLP_TEST_WRITE_PAUSE", "")
    if spec.partition(":")[0] == moment:
        sys.stderr.write("sphere-nlp: test pause at %s\n" % moment)
        sys.stderr.flush()
        time.sleep(float(spec.partition(":")[2] or 5))


def main(argv=None):
    """``sphere-nlp INPUT [options]`` or ``sphere-nlp COMMAND ...``; the exit status.

    Without ``argv`` (the console script) the process's signal handling starts here, before anything
    heavy is imported (:func:`sphere_nlp.interrupts.program_started`).
    """
    if argv is None:
        interrupts.program_started()
        try:
            return main(sys.argv[1:])
        finally:
            interrupts.program_finished()
    argv = list(argv)
    stderr = SafeStream(sys.stderr)
    if argv[:1] and argv[0] in SUBCOMMANDS:          # sphere-nlp resample MESH --icosphere 5 -o OUT
        interrupts.name_program("%s %s" % (PROG, argv[0]))
        return subcommand_main(argv[0])(argv[1:])
    unknown = unknown_command(argv[0]) if argv else None
    if unknown is not None:
        stderr.write("%s: error: %s\n" % (PROG, unknown))
        return unknown.exit_status
    try:
        named_png = png_given_a_name(argv)
        if named_png is not None:
            raise named_png
        parser = build_parser()
        args = parser.parse_args(join_negative_values(argv))
    except errors.UsageError as exc:
        stderr.write("%s: error: %s\n" % (PROG, exc))
        return exc.exit_status
    except SystemExit as exit_:        # --help
        return int(exit_.code or 0)
    from . import api  # noqa: F401  (loaded before the run takes the signals over: see interrupts)

    # Without a time limit, a long stage gets a note on how to bound it (see LONG_STAGE_S).
    progress = Progress(quiet=args.quiet, stream=stderr,
                        long_stage_s=LONG_STAGE_S if args.max_time is None else None)

    def interrupted(signum):
        stderr.write("%s: interrupted; nothing written (%s)\n" % (PROG, signal.Signals(signum).name))
        return 128 + signum

    try:
        with interrupts.handled_signals(), warnings_silenced(args.quiet):
            try:
                try:
                    status = run(args, progress)
                except errors.MeshInputError:
                    progress.clear_line()       # bad input: the error is the only line
                    raise
                finally:
                    progress.finish_line()      # an error message gets a line of its own
                if interrupts.pending_signal() is not None and not interrupts.is_committed():
                    raise interrupts.Interrupted(interrupts.pending_signal())   # one a library caught
            except errors.SphereNLPError as exc:
                if args.debug:
                    traceback.print_exc()
                stderr.write("%s: error: %s\n" % (PROG, exc))
                return exc.exit_status
            return status
    except KeyboardInterrupt as exc:
        return interrupted(getattr(exc, "signum", signal.SIGINT))
    except MemoryError:
        stderr.write("%s: error: out of memory; nothing written\n" % PROG)
        return 1
    except Exception as exc:  # a bug: still one line unless --debug
        if interrupts.program_signal() is not None:     # a signal broke a library (an import, say)
            return interrupted(interrupts.program_signal())
        if args.debug:
            traceback.print_exc()
        stderr.write("%s: internal error: %s: %s; nothing written (rerun with --debug for a traceback)\n"
                     % (PROG, type(exc).__name__, exc))
        return 1
