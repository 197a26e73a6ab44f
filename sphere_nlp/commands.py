"""The command line's shared parts: the registry of subcommands and the contract they all keep.

``sphere-nlp INPUT`` maps one mesh (:mod:`sphere_nlp.cli`); ``sphere-nlp COMMAND ...`` runs one of
:data:`SUBCOMMANDS`. Every subcommand builds its parser with :func:`subcommand_parser` and runs its
work through :func:`run_subcommand`, which gives it the main command's contract: usage and input
errors are one line ``sphere-nlp COMMAND: error: ...`` with exit status 2, found before any solving;
SIGINT / SIGTERM end it with 130 / 143 and one line saying what was left; anything else is one
"internal error" line, exit 1.

This module imports only the standard library and sphere_nlp's light modules (errors, interrupts),
so that the programs can take over the signals before numpy, CasADi or trimesh load; the
subcommands' modules are imported by name only when their command runs (no import circle).

>>> suggestion("resampel")
'resample'
>>> suggestion("bunny") is None
True
"""

import argparse
import difflib
import importlib
import math
import os
import re
import signal
import sys
import tempfile
import warnings
from contextlib import contextmanager
from pathlib import Path

from . import errors, interrupts

PROG = "sphere-nlp"

# name: (module, function, one line for --help). The order is the order of --help.
SUBCOMMANDS = {
    "reproduce": ("sphere_nlp.reproduce", "main",
                  "redraw the paper's Fig. 3 (a cylinder mapped six ways) with its numbers"),
    "compare": ("sphere_nlp.compare", "main",
                "map meshes with sphere_nlp and with baseline methods; tabulate validity and distortion"),
    "batch": ("sphere_nlp.batch", "main",
              "map many meshes with the same options (resumable; worker processes or a Dask cluster)"),
    "resample": ("sphere_nlp.resample", "resample_main",
                 "remesh a shape on an icosphere through its sphere map"),
    "transfer": ("sphere_nlp.resample", "transfer_main",
                 "carry per-vertex values of one shape to another through their sphere maps"),
    "morph": ("sphere_nlp.resample", "morph_main",
              "in-between shapes from one mesh to another through their sphere maps"),
    "picture": ("sphere_nlp.picture", "main",
                "draw the picture of a map written earlier (a mesh and its sphere), without solving"),
}


def subcommand_main(name):
    """The ``main(argv)`` function of the subcommand ``name``."""
    module, function, _ = SUBCOMMANDS[name]
    return getattr(importlib.import_module(module), function)


def subcommand_lines(width=10):
    """The subcommands, one line each, for --help."""
    return "\n".join("  %-*s %s" % (width, name, line) for name, (_, _, line) in SUBCOMMANDS.items())


def suggestion(word):
    """The subcommand ``word`` is probably a misspelling of, or None."""
    close = difflib.get_close_matches(word.lower(), SUBCOMMANDS, n=1, cutoff=0.6)
    return close[0] if close else None


def unknown_command(word):
    """A UsageError for a first argument that is neither a subcommand nor an existing file, or None
    when ``word`` looks like a file name (a path or a name with an extension: a missing mesh is
    then reported as such)."""
    if word.startswith("-") or word in SUBCOMMANDS or os.path.lexists(word):
        return None
    close = suggestion(word)
    looks_like_file = os.sep in word or "/" in word or Path(word).suffix
    if close and not Path(word).suffix:
        return errors.UsageError("unknown command %r (did you mean %r?)" % (word, close))
    if looks_like_file:
        return None
    return errors.UsageError("unknown command %r, and no file of that name; the commands are %s "
                             "(see %s --help)" % (word, ", ".join(SUBCOMMANDS), PROG))


class UsageParser(argparse.ArgumentParser):
    """argparse with its errors raised as UsageError: one line, the tool's own prefix."""

    def error(self, message):
        raise errors.UsageError("%s (see %s --help)" % (message, self.prog))


def subcommand_parser(name, description, epilog=None):
    """The argument parser of ``sphere-nlp NAME``: its usage errors are one line (see :func:`run_subcommand`)."""
    return UsageParser(prog="%s %s" % (PROG, name), description=description, epilog=epilog,
                       formatter_class=argparse.RawDescriptionHelpFormatter)


class SafeStream:
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


@contextmanager
def warnings_silenced(quiet):
    """With ``-q`` (``quiet`` true) Python warnings inside the block are not printed, since ``-q``
    prints only errors; worker processes started inside (``batch``) inherit that through
    PYTHONWARNINGS, which a new interpreter reads as it starts."""
    if not quiet:
        yield
        return
    saved = os.environ.get("PYTHONWARNINGS")
    os.environ["PYTHONWARNINGS"] = "ignore"
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            yield
    finally:
        if saved is None:
            os.environ.pop("PYTHONWARNINGS", None)
        else:
            os.environ["PYTHONWARNINGS"] = saved


def run_subcommand(parser, argv, body, interrupted="nothing more written", check=None, failed=None):
    """Run a subcommand with the main command's contract; its exit status.

    ``check(args)``, if given, checks every input, option value and output path and raises on the
    first problem; it runs before ``body(args, say)``, which does the work and returns the exit
    status. ``say(line)`` prints a progress line ``PROG: line`` unless ``-q``, so a rejection is
    always the only line. Bad usage and input (:class:`~sphere_nlp.errors.SphereNLPError`) and file
    system errors end it with one line ``PROG: error: ...`` (exit 2 for usage, input and files);
    SIGINT / SIGTERM with one line saying ``interrupted`` and what was left (``interrupted``, a
    string or a function of ``args``), exit 130 / 143; a failed solve or certificate, running out of
    memory and anything else (one "internal error" line) exit 1 with a line that ends with what was
    left (``failed``, as ``interrupted``, which it defaults to).
    """
    stderr = SafeStream(sys.stderr)
    prog = parser.prog
    interrupts.name_program(prog)
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

    def left(what):
        return what(args) if callable(what) else what

    def interrupted_line(signum):
        stderr.write("%s: interrupted; %s (%s)\n" % (prog, left(interrupted), signal.Signals(signum).name))
        return 128 + signum

    def failure_line(message):
        stderr.write("%s: %s; %s\n" % (prog, message, left(interrupted if failed is None else failed)))
        return 1

    try:
        with interrupts.handled_signals(), warnings_silenced(getattr(args, "quiet", False)):
            if check is not None:
                check(args)
            status = body(args, say)
            signum = interrupts.pending_signal()
            if signum is not None and not interrupts.is_committed():
                raise interrupts.Interrupted(signum)     # a signal a library caught and went on
            return status
    except KeyboardInterrupt as exc:
        return interrupted_line(getattr(exc, "signum", signal.SIGINT))
    except errors.SphereNLPError as exc:
        if exc.exit_status == 1:                # the solve or the certificate failed
            return failure_line("error: %s" % exc)
        stderr.write("%s: error: %s\n" % (prog, exc))
        return exc.exit_status
    except OSError as exc:
        if interrupts.program_signal() is not None:
            return interrupted_line(interrupts.program_signal())
        where = "%s: " % exc.filename if getattr(exc, "filename", None) else ""
        stderr.write("%s: error: %s%s\n" % (prog, where, exc.strerror or exc))
        return 2
    except MemoryError:
        return failure_line("error: out of memory")
    except Exception as exc:  # a bug: still one line
        if interrupts.program_signal() is not None:    # a signal broke a library (an import, say)
            return interrupted_line(interrupts.program_signal())
        return failure_line("internal error: %s: %s" % (type(exc).__name__, exc))


# ----------------------------------------------------------------------------------- output paths

def same_file(a, b):
    """Whether two paths name one file (the same path, or links to one existing file)."""
    if os.path.abspath(a) == os.path.abspath(b):
        return True
    try:
        return os.path.realpath(a) == os.path.realpath(b) or os.path.samefile(a, b)
    except OSError:
        return False


def check_output_paths(inputs, outputs):
    """Raise UsageError unless every output can be written, before anything is solved.

    ``inputs`` is a list of (what, path) the run reads (a path alone means "the input file");
    ``outputs`` a list of (option, path). Each output must differ from every input and from the
    other outputs, must not be a folder, and its folder must exist and take a new file of that
    name: a temporary file named as :func:`~sphere_nlp.mesh_io.atomic_output` names it is created
    there and removed, which also catches read-only folders and names too long.
    """
    if isinstance(inputs, (str, os.PathLike)):
        inputs = [("the input file", inputs)]
    inputs = [(what, path) for what, path in inputs if path]
    for k, (option, path) in enumerate(outputs):
        for what, source in inputs:
            if same_file(path, source):
                raise errors.UsageError("%s %s is %s: choose another name (an input is never replaced)"
                                        % (option, path, what))
        for other_option, other in outputs[:k]:
            if same_file(path, other):
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


def check_output_folder(option, folder):
    """Raise UsageError unless ``folder`` is a folder files can be created in, or can be created.

    Nothing is created: a missing folder is checked through its nearest existing parent.
    """
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise errors.UsageError("cannot write to %s %s: it is a file, not a folder" % (option, folder))
    existing = folder
    while not existing.exists():
        parent = existing.parent
        if parent == existing:
            break
        existing = parent
    if existing.exists() and not existing.is_dir():
        raise errors.UsageError("cannot create %s %s: %s is a file" % (option, folder, existing))
    if not os.access(existing, os.W_OK | os.X_OK):
        raise errors.UsageError("cannot write to %s %s: permission denied (%s)" % (option, folder, existing))


# ------------------------------------------------------------------------------ picture options
# Shared by the main command and ``picture``: both draw the same picture from the same options.

UP_CHOICES = ("x", "y", "z", "+x", "+y", "+z", "-x", "-y", "-z")


def view_argument(text):
    """``AZ,EL`` in degrees, for --view: a finite azimuth and an elevation in [-90, 90] (a NaN
    camera draws blank panels).

    >>> view_argument("-60,20")
    (-60.0, 20.0)
    """
    try:
        azimuth, elevation = (float(word) for word in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError("expected AZIMUTH,ELEVATION in degrees, e.g. -60,20; got %r" % text)
    if not (math.isfinite(azimuth) and math.isfinite(elevation)):
        raise argparse.ArgumentTypeError("the azimuth and elevation must be finite numbers of degrees, "
                                         "not %r" % text)
    if not -90 <= elevation <= 90:
        raise argparse.ArgumentTypeError("the elevation must be between -90 and 90 degrees, not %g" % elevation)
    return azimuth, elevation


# Options whose value may start with "-" (a negative azimuth): argparse would take "-60,20" for an
# option, so "--view -60,20" becomes "--view=-60,20" before parsing.
NEGATIVE_VALUE_OPTIONS = ("--view",)
_NUMBERS = re.compile(r"-[0-9.]+(e[-+]?[0-9]+)?(,[-+]?[0-9.]+(e[-+]?[0-9]+)?)*", re.I)


def join_negative_values(argv):
    """``argv`` with ``--view -60,20`` written ``--view=-60,20`` (see NEGATIVE_VALUE_OPTIONS).

    >>> join_negative_values(["m.off", "--view", "-60,20", "-q"])
    ['m.off', '--view=-60,20', '-q']
    """
    joined, k = [], 0
    while k < len(argv):
        if argv[k] in NEGATIVE_VALUE_OPTIONS and k + 1 < len(argv) and _NUMBERS.fullmatch(argv[k + 1]):
            joined.append("%s=%s" % (argv[k], argv[k + 1]))
            k += 2
        else:
            joined.append(argv[k])
            k += 1
    return joined
