"""Stopping a run cleanly: SIGINT / SIGTERM, and a wall-clock deadline for the whole run.

IPOPT runs sphere_nlp's Python callbacks and catches whatever they raise: a KeyboardInterrupt raised
inside one ends only that IPOPT stage (status NonIpopt_Exception_Thrown, or an evaluation error that
IPOPT steps around), and the solve would carry on with its next stage. So a signal is *recorded*
here as well as raised; the IPOPT iteration callback asks IPOPT to stop while one is pending
(:func:`stop_requested`), and :meth:`sphere_nlp.nlp.AngleNLP.solve` raises it again once IPOPT has
returned (:func:`raise_if_interrupted`).

The same iteration callback enforces a run's deadline (:func:`deadline`): every IPOPT stage stops at
its first iteration past it, so ``max_time`` bounds the whole run, not each stage.

A program (``python -m sphere_nlp``, the ``sphere-nlp`` script) calls :func:`program_started` as its
first statement, before numpy, CasADi or trimesh are imported: until its run takes the signals over
with :func:`handled_signals`, a SIGINT or SIGTERM ends the process at once with 128 + its number and
one line (nothing has been written by then), and after the run a signal no longer changes the exit
status. Only the first signal counts: one arriving while the run is already stopping is ignored, so
a second Ctrl-C cannot cut the clean-up short.

Example
-------
>>> with handled_signals():
...     raise_if_interrupted()          # nothing pending: returns
"""

import math
import os
import signal
import sys
import threading
import time
from contextlib import contextmanager

SIGNALS = (signal.SIGINT, signal.SIGTERM)


class Interrupted(KeyboardInterrupt):
    """A run ended by a signal; ``exit_status`` is 128 + the signal number (130 SIGINT, 143 SIGTERM)."""

    def __init__(self, signum=signal.SIGINT):
        super().__init__("interrupted by %s" % signal.Signals(signum).name)
        self.signum = int(signum)
        self.exit_status = 128 + self.signum


_pending = None           # the first signal received while handled_signals() is active
_deadline = math.inf      # time.perf_counter() value at which IPOPT stages stop
_deferred = 0             # > 0 inside defer_signals(): record, do not raise
_committed = False        # committed() was called inside the current handled_signals()
_program = None           # the program's name for its messages, once program_started() ran
_program_signal = None    # the first signal the program received (never cleared)
_program_clock = None     # time.perf_counter() at program_started()
_run_over = False         # the program's run has left handled_signals(): its exit status stands


def _handler(signum, frame):
    global _pending, _program_signal
    if _program_signal is None and _program_clock is not None:
        _program_signal = signum
    if _pending is not None:
        return                  # already stopping: the first signal decides, the clean-up goes on
    _pending = signum
    if not _deferred:
        raise Interrupted(signum)


def _unraisable_hook(unraisable):
    """sys.unraisablehook inside :func:`handled_signals`. A signal that arrives while a finaliser
    runs (a ``__del__``, a weakref callback: CasADi and matplotlib objects freed mid-run) is raised
    there, where Python cannot propagate it and prints it as "Exception ignored in ..." with a
    traceback. It is recorded already (the handler sets the pending signal first), and the run
    stops on it at its next check, so nothing is printed; anything else goes to the usual hook."""
    if isinstance(unraisable.exc_value, Interrupted):
        return
    sys.__unraisablehook__(unraisable)


def _program_handler(signum, frame):
    """Outside the run's own handling: during start-up end at once (nothing is written yet); after
    the run, or while it is stopping, keep the status it has."""
    global _program_signal
    if _program_signal is not None or _run_over:
        return
    _program_signal = signum
    try:
        os.write(2, ("%s: interrupted; nothing written (%s)\n"
                     % (_program, signal.Signals(signum).name)).encode())
    except OSError:
        pass
    os._exit(128 + signum)


def program_started(name="sphere-nlp"):
    """Install the program's SIGINT / SIGTERM handling; call first thing (main thread only).

    ``name`` is the prefix of the one line a signal during start-up prints. Calling it again only
    changes the name. Returns the seconds since the first call (0.0 the first time).
    """
    global _program, _program_clock
    _program = name
    if _program_clock is None:
        _program_clock = time.perf_counter()
        if threading.current_thread() is threading.main_thread():
            for s in SIGNALS:
                signal.signal(s, _program_handler)
    return time.perf_counter() - _program_clock


def program_finished():
    """The program's exit status is settled: SIGINT and SIGTERM are ignored from here on.

    Python's finalization puts the default handlers back for the signals it handles, so a second
    signal while the interpreter shuts down (freeing numpy, CasADi) would kill the process instead
    of letting it exit with its status; an ignored signal stays ignored.
    """
    if _program_clock is not None and threading.current_thread() is threading.main_thread():
        for s in SIGNALS:
            signal.signal(s, signal.SIG_IGN)


def name_program(name):
    """The prefix of the start-up signal line from now on, if :func:`program_started` ran."""
    global _program
    if _program_clock is not None:
        _program = name


def program_elapsed():
    """Seconds since :func:`program_started` (0.0 if it was never called)."""
    return 0.0 if _program_clock is None else time.perf_counter() - _program_clock


def program_signal():
    """The first signal the program received, or None (see :func:`program_started`)."""
    return _program_signal


def pending_signal():
    """The signal number recorded since :func:`handled_signals` began, or None."""
    return _pending


def raise_if_interrupted():
    """Raise :class:`Interrupted` if a signal has been recorded."""
    if _pending is not None:
        raise Interrupted(_pending)


def check_before_write():
    """Raise :class:`Interrupted` if a signal is pending and not deferred: called before every file
    is written, so that one a library caught (``except BaseException``) still stops the writes."""
    if _pending is not None and not _deferred:
        raise Interrupted(_pending)


def request_stop(signum=signal.SIGTERM):
    """Ask the running solve to stop as a signal would (from another thread, e.g. a Dask task's
    watcher): IPOPT stops at its next iteration and :class:`Interrupted` is raised."""
    global _pending
    if _pending is None:
        _pending = signum


def clear_stop():
    """Forget a :func:`request_stop` (a worker process that goes on with other work)."""
    global _pending
    _pending = None


def deadline_passed():
    return time.perf_counter() >= _deadline


def seconds_left():
    """Seconds until the run's deadline (inf without one)."""
    return _deadline - time.perf_counter()


def stop_requested():
    """True when IPOPT should stop now: a signal is pending or the run's deadline has passed."""
    return _pending is not None or time.perf_counter() >= _deadline


@contextmanager
def handled_signals(signals=SIGNALS, only_default=False):
    """Record and raise ``signals`` as :class:`Interrupted` inside the block (main thread only).

    The previous handlers come back afterwards, and the record is cleared on entry and exit. Inside
    another such block this one changes nothing. With ``only_default``, a signal whose handler is not
    Python's default (or the start-up handling of :func:`program_started`) is left alone, such as a
    program's own SIGINT handler.
    """
    global _pending, _run_over
    if (threading.current_thread() is not threading.main_thread()
            or signal.getsignal(signal.SIGINT) is _handler):
        yield
        return
    global _deferred, _committed
    _pending, saved, _committed = None, _deferred, False
    defaults = {signal.SIGINT: signal.default_int_handler, signal.SIGTERM: signal.SIG_DFL}
    if _program_clock is not None:      # the program's own start-up handling counts as the default
        defaults = dict.fromkeys(SIGNALS, _program_handler)
    previous = {}
    hook = sys.unraisablehook
    try:
        sys.unraisablehook = _unraisable_hook
        for s in signals:
            if not only_default or signal.getsignal(s) is defaults.get(s):
                previous[s] = signal.signal(s, _handler)
        yield
    finally:
        if _program_clock is not None and previous:
            _run_over = True                # signals from here on: see _program_handler
        for s, handler in previous.items():
            signal.signal(s, handler)
        sys.unraisablehook = hook
        _pending, _deferred, _committed = None, saved, False


def is_committed():
    """Whether :func:`committed` was called inside the current :func:`handled_signals`."""
    return _committed


def committed():
    """The run's outputs are in place: until :func:`handled_signals` ends, signals are only recorded.

    Called by :func:`sphere_nlp.mesh_io.output_transaction` once its renames are final, so that no
    signal afterwards turns a finished run into an interrupted one. Outside handled_signals, nothing.
    """
    global _deferred, _committed
    if signal.getsignal(signal.SIGINT) is _handler and not _committed:
        _committed = True
        _deferred += 1


@contextmanager
def defer_signals():
    """Inside the block a signal is only recorded (see :func:`pending_signal`), not raised.

    For steps that must not be cut in half, such as renaming a run's outputs into place.
    """
    global _deferred
    _deferred += 1
    try:
        yield
    finally:
        _deferred -= 1


@contextmanager
def deadline(seconds):
    """IPOPT stages started inside the block stop at their first iteration ``seconds`` from now.

    ``None`` means no deadline. Nested deadlines keep the earlier one.
    """
    global _deadline
    previous = _deadline
    if seconds is not None:
        _deadline = min(_deadline, time.perf_counter() + float(seconds))
    try:
        yield
    finally:
        _deadline = previous


@contextmanager
def extended_deadline(seconds):
    """Move a pending deadline ``seconds`` later inside the block (no deadline stays none).

    For a short stage that must run after the deadline to turn the stopped iterate into a result
    (``on_limit="project"``).
    """
    global _deadline
    previous = _deadline
    if math.isfinite(_deadline):
        _deadline = max(_deadline, time.perf_counter()) + float(seconds)
    try:
        yield
    finally:
        _deadline = previous
