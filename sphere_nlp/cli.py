"""Command line: ``python -m sphere_nlp INPUT [options]`` (a thin layer over :func:`parameterize`).

Exit status: 0 a certified sphere was written; 1 the solve or the certificate failed (nothing
written); 2 bad input or bad usage, found before any solving (nothing written); 130 / 143 ended by
SIGINT / SIGTERM (nothing written or replaced). All outputs of a run are renamed into place together,
only after everything succeeded (:func:`sphere_nlp.mesh_io.output_transaction`).
"""

import argparse
import math
import os
import signal
import sys
import tempfile
import time
import traceback
from pathlib import Path

from . import __version__, errors, interrupts
from .mesh_io import check_mesh_path, output_transaction
from .nlp import FORMULATIONS
from .solve import ON_LIMIT
from .targets import CORNER_WEIGHTINGS, MODES

# Three runnable examples (tests/test_ux.py runs each of them).
EXAMPLES = """examples:
  sphere-nlp models/cylinder.off
  sphere-nlp models/cylinder.off -o cylinder.obj --png cylinder.png
  sphere-nlp models/cylinder.off --target equal-areas --textured-input painted.obj --report run.json
"""


PROG = "sphere-nlp"


class _Parser(argparse.ArgumentParser):
    """argparse with its errors raised as UsageError: one line, the tool's own prefix."""

    def error(self, message):
        raise errors.UsageError("%s (see %s --help)" % (message, self.prog))


def build_parser():
    parser = _Parser(
        prog=PROG,
        description="Map a closed genus-0 triangle mesh onto the unit sphere without overlaps\n"
                    "(Sheffer, Gotsman & Dyn 2004), certified before anything is written.\n"
                    "`sphere-nlp reproduce fig3 --out DIR` redraws the paper's Fig. 3;\n"
                    "`sphere-nlp compare MESH... --out DIR` compares sphere_nlp with the baselines.",
        epilog=EXAMPLES, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("input", help="input mesh (OFF, OBJ, PLY, STL, anything trimesh reads)")
    parser.add_argument("--version", action="version", version="sphere-nlp " + __version__)
    out = parser.add_argument_group("output (each written atomically, only for a certified sphere)")
    out.add_argument("-o", "--output", metavar="OUT", help="sphere mesh, .off/.obj/.ply; .obj carries longitude/latitude "
                                            "texture coordinates (default: <input name without its last "
                                            "extension>.sphere.off here)")
    out.add_argument("--png", metavar="OUT.png",
                     help="picture: mesh and sphere coloured by distortion, mesh checkerboarded")
    out.add_argument("--png-measure", choices=("area", "angle"),
                     help="colouring of the picture: log area ratio or angle distortion (default: the "
                          "one the target mode does not optimise)")
    out.add_argument("--view", metavar="AZ,EL", type=_view,
                     help="camera azimuth and elevation of the picture, degrees (default: the side "
                          "with the most projected area)")
    out.add_argument("--textured-input", metavar="OUT.obj",
                     help="the input mesh with the sphere's texture coordinates, to paint or texture")
    out.add_argument("--texture", metavar="NAME.png",
                     help="with an OBJ output: write a checkerboard texture NAME.png and an .mtl beside "
                          "each OBJ, referenced by it, so viewers show the map")
    out.add_argument("--report", metavar="R.json", help="run statistics as JSON (also on failure)")
    out.add_argument("--save-solution", metavar="S.npz",
                     help="vertices, faces, angles, excess and targets as .npz")
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
                        help="keep every spherical corner >= F x its target angle (default 0.1, 0 in the "
                             "area modes), and in the angle modes every corner whose target is below 10 "
                             "degrees >= half of it (0: no corner floor at all)")
    method.add_argument("--area-floor", type=float, metavar="F",
                        help="keep every spherical triangle >= F x the mean area 4 pi / t (0: off)")
    method.add_argument("--start", metavar="SPHERE",
                        help="start from an earlier sphere of this mesh (one sphere-nlp wrote for it, or for "
                             "a mesh with the same triangles); near the targets the area modes then skip "
                             "their walk, and solving a map again takes a few iterations")
    limits = parser.add_argument_group("solver limits (reaching one is a failure, unless --on-limit project)")
    limits.add_argument("--max-iter", type=int, metavar="N", help="IPOPT iteration limit per stage (>= 1)")
    limits.add_argument("--max-time", type=float, metavar="S",
                        help="wall-clock limit of the whole run, seconds (> 0; the solve stops at its first "
                             "IPOPT iteration past it)")
    limits.add_argument("--on-limit", choices=ON_LIMIT, default="fail",
                        help="when the main stage reaches a limit: fail (default), or project its last "
                             "iterate onto the constraints and write that certified, not optimal, sphere")
    misc = parser.add_argument_group("messages")
    misc.add_argument("-q", "--quiet", action="store_true", help="print only errors")
    misc.add_argument("--debug", action="store_true", help="show tracebacks")
    return parser


# A solve stage running this long without --max-time gets one note on how to bound it: the area
# modes' main stage takes 15-35 minutes at 43k-50k vertices and had not converged after 2.5 hours at
# 173k (README, Sizes and speed).
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
        # A terminal line can change often; a log file gets a line every few seconds.
        interval = 0.2 if self.tty else 5.0
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
        if not self.quiet:
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
    if not result.converged:
        line += ("; NOT OPTIMAL: the solve stopped at its limit (IPOPT %s after %d iterations, objective "
                 "%.6g) and its last iterate was projected onto the constraints"
                 % (result.status, result.iterations, result.objective))
    return line


def floor_note(result, corner_floor_given):
    """A line on the floors after a certified run, or None: how many corners and triangles ended
    on their floors, or, in an area mode run without a corner floor, how many corners collapsed
    below 0.1 x their target and how to keep them."""
    area_mode = result.target.endswith("-areas")
    collapsed = result.usability()["corners_below_fraction"] if area_mode and not corner_floor_given else 0
    if collapsed:
        return ("%d of %d corners ended below 0.1 x their target angle: reaching the areas shears "
                "their triangles; --corner-floor 0.1 keeps them, at a cost in area error (docs/tuning.md)"
                % (collapsed, result.angles.size))
    parts = []
    if result.floor_corners and (corner_floor_given or not area_mode):
        parts.append("%d corners (--corner-floor)" % result.floor_corners)
    if result.floor_triangles:
        parts.append("%d triangles (--area-floor)" % result.floor_triangles)
    return " and ".join(parts) + " ended on their floors" if parts else None


def _view(text):
    """``AZ,EL`` in degrees, for --view."""
    try:
        azimuth, elevation = (float(word) for word in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError("expected AZIMUTH,ELEVATION in degrees, e.g. -60,20; got %r" % text)
    return azimuth, elevation


def _check_suffix(path, suffix, what):
    if path and Path(path).suffix.lower() != suffix:
        raise errors.UsageError("cannot write %s: %s must end in %s" % (path, what, suffix))


def _texture_beside(obj_path, texture):
    """Where --texture goes for an OBJ: a bare file name beside the OBJ, a path as given."""
    if not texture:
        return None
    texture = Path(texture)
    return Path(obj_path).parent / texture if texture.parent == Path(".") else texture


def default_output(input_path):
    """``<input name without its last extension>.sphere.off``, in the current folder.

    ``knight.v1.off`` gives ``knight.v1.sphere.off`` (not ``knight.sphere.off``, which ``knight.v2.off``
    would overwrite), ``.hidden.off`` gives ``.hidden.sphere.off``.
    """
    return Path(Path(input_path).stem + ".sphere.off")


def _same_file(a, b):
    """Whether two paths name one file (the same path, or links to one existing file)."""
    if os.path.abspath(a) == os.path.abspath(b):
        return True
    try:
        return os.path.realpath(a) == os.path.realpath(b) or os.path.samefile(a, b)
    except OSError:
        return False


def check_output_paths(input_path, outputs):
    """Raise UsageError unless every output can be written, before anything is solved.

    ``outputs`` is a list of (option, path). Each must differ from the input and from the others,
    must not be a folder, and its folder must exist and take a new file of that name: a temporary
    file named as :func:`~sphere_nlp.mesh_io.atomic_output` names it is created there and removed,
    which also catches read-only folders and names too long.
    """
    for k, (option, path) in enumerate(outputs):
        if _same_file(path, input_path):
            raise errors.UsageError("%s %s is the input file: choose another name (the input is never "
                                    "replaced)" % (option, path))
        for other_option, other in outputs[:k]:
            if _same_file(path, other):
                raise errors.UsageError("%s and %s both name %s: each output needs its own file"
                                        % (other_option, option, path))
        path = Path(path)
        folder = path.parent if str(path.parent) else Path(".")
        try:
            if path.is_dir():
                raise errors.UsageError("cannot write %s %s: it is a folder" % (option, path))
            if not folder.is_dir():
                raise errors.UsageError("cannot write %s %s: %s" % (
                    option, path, "no such folder %s" % folder if not folder.exists()
                    else "%s is not a folder" % folder))
            fd, probe = tempfile.mkstemp(prefix="." + path.name + ".", suffix=".tmp", dir=folder)
            os.close(fd)
            os.unlink(probe)
        except OSError as exc:
            raise errors.UsageError("cannot write %s %s: %s" % (option, path, exc.strerror or exc)) from None


def check_arguments(args):
    """Option values the parser cannot check itself (UsageError), before the mesh is read."""
    from .api import _check_arguments

    for option, value in (("--max-time", args.max_time), ("--angle-weight", args.angle_weight),
                          ("--area-weight", args.area_weight)):
        if value is not None and not math.isfinite(value):
            raise errors.UsageError("%s must be a finite number, not %s" % (option, value))
    if args.max_time is not None and args.max_time <= 0:
        raise errors.UsageError("--max-time must be > 0 seconds, not %g" % args.max_time)
    if args.max_iter is not None and args.max_iter <= 0:
        raise errors.UsageError("--max-iter must be >= 1, not %d" % args.max_iter)
    try:
        _check_arguments(angle_weight=args.angle_weight, area_weight=args.area_weight,
                         max_iter=args.max_iter, max_time=args.max_time, ipopt_options=None)
    except errors.UsageError as exc:           # the API's words for the options' values
        raise errors.UsageError(str(exc).replace("angle_weight", "--angle-weight")
                                .replace("area_weight", "--area-weight").replace("max_iter", "--max-iter")
                                .replace("max_time", "--max-time")) from None


def run(args, progress):
    from .api import parameterize, solve_failure_message
    from .mesh_io import load_mesh

    input_path = Path(args.input)
    output = Path(args.output) if args.output else default_output(input_path)
    # Every option and output path is checked before the (possibly long) solve.
    check_arguments(args)
    check_mesh_path(output)
    _check_suffix(args.png, ".png", "a picture")
    _check_suffix(args.textured_input, ".obj", "a textured mesh")
    _check_suffix(args.texture, ".png", "a texture")
    is_obj = output.suffix.lower() == ".obj"
    if args.texture and not is_obj and not args.textured_input:
        raise errors.UsageError("--texture needs an OBJ output (-o X.obj or --textured-input X.obj)")
    outputs = [("-o" if args.output else "the default output", output)]
    outputs += [(option, Path(path)) for option, path in
                (("--png", args.png), ("--textured-input", args.textured_input),
                 ("--save-solution", args.save_solution), ("--report", args.report)) if path]
    # The texture image goes beside each OBJ written (one file when both OBJs share a folder).
    textures = {_texture_beside(obj, args.texture).resolve() for obj in
                ([output] if is_obj else []) + ([Path(args.textured_input)] if args.textured_input else [])
                if args.texture}
    outputs += [("--texture", path) for path in sorted(textures)]
    check_output_paths(input_path, outputs)

    def on_stage(name):
        # Announced once the mesh has been read and validated, so bad input gets only its error line.
        if name == "solve":
            progress.say("sphere-nlp: mapping %s (target %s)" % (input_path, args.target))
        progress.stage(name)

    start = None
    if args.start:
        # Read here; parameterize checks it against the mesh before the solve is announced.
        try:
            start, _ = load_mesh(args.start)
        except errors.MeshInputError as exc:
            raise errors.UsageError("--start: %s" % exc) from None
    result = parameterize(str(input_path), target=args.target, angle_weight=args.angle_weight,
                          area_weight=args.area_weight, formulation=args.formulation,
                          corner_weighting=args.corner_weighting, corner_floor=args.corner_floor,
                          area_floor=args.area_floor,
                          max_iter=args.max_iter, max_time=args.max_time, on_limit=args.on_limit,
                          progress=progress.iteration,
                          on_stage=on_stage, start=start, check=False)
    for repair in result.repairs:
        progress.say("repaired: " + repair)
    if not result.success:
        if args.report:
            result.write_report(args.report)
        if not result.solved:
            raise errors.SolveError(solve_failure_message(result.status, result.iterations)
                                    + "; nothing written")
        raise errors.CertificateError("the sphere failed its certificate (%s; IPOPT status %s); nothing "
                                      "written" % (result.certificate.reason, result.status))
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
        if args.png:
            progress.stage("write (picture)")
            result.write_png(args.png, measure=args.png_measure, view=args.view)
        if args.report:
            result.write_report(args.report)
        _write_hook("staged")
    # Committed (interrupts.committed): from here on a signal no longer undoes the run.
    progress.say(summary_line(output, result))
    note = floor_note(result, bool(args.corner_floor))
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


class _SafeStream:
    """stderr that never fails the run: a closed or broken stream (``2>&-``, a closed pipe) just
    loses the message."""

    def __init__(self, stream):
        self.stream = stream

    def write(self, text):
        try:
            if self.stream is not None:
                self.stream.write(text)
        except (OSError, ValueError):           # closed, broken pipe, full disk
            self.stream = None

    def flush(self):
        try:
            if self.stream is not None:
                self.stream.flush()
        except (OSError, ValueError):
            self.stream = None

    def isatty(self):
        try:
            return self.stream is not None and self.stream.isatty()
        except (OSError, ValueError):
            return False


def subcommand_parser(name, description):
    """The argument parser of ``sphere-nlp NAME``: its usage errors are one line (see :func:`run_subcommand`)."""
    return _Parser(prog="%s %s" % (PROG, name), description=description)


def run_subcommand(parser, argv, body, interrupted="nothing more written"):
    """Run a subcommand with the main command's contract; its exit status.

    ``body(args, say)`` does the work and returns the exit status; ``say(line)`` prints a progress
    line unless ``-q``. Bad usage and input (:class:`~sphere_nlp.errors.SphereNLPError`) and file
    system errors end it with one line ``PROG: error: ...`` (exit 2 for usage, input and files);
    SIGINT / SIGTERM with one line saying ``interrupted`` and what was left (``interrupted``, a
    string or a function of ``args``), exit 130 / 143; anything else with one "internal error" line.
    """
    stderr = _SafeStream(sys.stderr)
    prog = parser.prog
    try:
        args = parser.parse_args(argv)
    except errors.UsageError as exc:
        stderr.write("%s: error: %s\n" % (prog, exc))
        return exc.exit_status
    except SystemExit as exit_:        # --help
        return int(exit_.code or 0)

    def say(line):
        if not getattr(args, "quiet", False):
            stderr.write("%s: %s\n" % (prog, line))
            stderr.flush()

    try:
        with interrupts.handled_signals():
            return body(args, say)
    except errors.SphereNLPError as exc:
        stderr.write("%s: error: %s\n" % (prog, exc))
        return exc.exit_status
    except OSError as exc:
        where = "%s: " % exc.filename if getattr(exc, "filename", None) else ""
        stderr.write("%s: error: %s%s\n" % (prog, where, exc.strerror or exc))
        return 2
    except KeyboardInterrupt as exc:
        signum = getattr(exc, "signum", signal.SIGINT)
        left = interrupted(args) if callable(interrupted) else interrupted
        stderr.write("%s: interrupted; %s (%s)\n" % (prog, left, signal.Signals(signum).name))
        return 128 + signum
    except MemoryError:
        stderr.write("%s: error: out of memory\n" % prog)
        return 1
    except Exception as exc:  # a bug: still one line
        stderr.write("%s: internal error: %s: %s\n" % (prog, type(exc).__name__, exc))
        return 1


def main(argv=None):
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["reproduce"]:      # `python -m sphere_nlp reproduce fig3 --out DIR`
        from .reproduce import main as reproduce_main

        return reproduce_main(argv[1:])
    if argv[:1] == ["compare"]:        # `python -m sphere_nlp compare MESH... --out DIR`
        from .compare import main as compare_main

        return compare_main(argv[1:])
    if argv[:1] == ["resample"]:       # `python -m sphere_nlp resample MESH --icosphere 5 -o OUT`
        from .resample import resample_main

        return resample_main(argv[1:])
    if argv[:1] == ["morph"]:          # `python -m sphere_nlp morph A B --frames 30 --out DIR`
        from .resample import morph_main

        return morph_main(argv[1:])
    if argv[:1] == ["transfer"]:       # `python -m sphere_nlp transfer A B --values V.npy -o OUT.npy`
        from .resample import transfer_main

        return transfer_main(argv[1:])
    if argv[:1] == ["batch"]:          # `python -m sphere_nlp batch INPUT... --out DIR`
        from .batch import main as batch_main

        return batch_main(argv[1:])
    stderr = _SafeStream(sys.stderr)
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except errors.UsageError as exc:
        stderr.write("%s: error: %s\n" % (PROG, exc))
        return exc.exit_status
    except SystemExit as exit_:        # --help
        return int(exit_.code or 0)
    # Without a time limit, a long stage gets a note on how to bound it (see LONG_STAGE_S).
    progress = Progress(quiet=args.quiet, stream=stderr,
                        long_stage_s=LONG_STAGE_S if args.max_time is None else None)
    try:
        with interrupts.handled_signals():
            try:
                try:
                    return run(args, progress)
                except errors.MeshInputError:
                    progress.clear_line()       # bad input: the error is the only line
                    raise
                finally:
                    progress.finish_line()      # an error message gets a line of its own
            except errors.SphereNLPError as exc:
                if args.debug:
                    traceback.print_exc()
                stderr.write("%s: error: %s\n" % (PROG, exc))
                return exc.exit_status
    except KeyboardInterrupt as exc:
        signum = getattr(exc, "signum", signal.SIGINT)
        stderr.write("%s: interrupted; nothing written (%s)\n" % (PROG, signal.Signals(signum).name))
        return 128 + signum
    except MemoryError:
        stderr.write("%s: error: out of memory; nothing written\n" % PROG)
        return 1
    except Exception as exc:  # a bug: still one line unless --debug
        if args.debug:
            traceback.print_exc()
        stderr.write("%s: internal error: %s: %s; nothing written (rerun with --debug for a traceback)\n"
                     % (PROG, type(exc).__name__, exc))
        return 1
