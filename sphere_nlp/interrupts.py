"""Stopping a run cleanly: SIGINT / SIGTERM, and a wall-clock deadline for the whole run.

IPOPT runs sphere_nlp's Python callbacks and catches whatever they raise: a KeyboardInterrupt raised
inside one ends only that IPOPT stage (status NonIpopt_Exception_Thrown, or an evaluation error that
IPOPT steps around), and the solve would carry on with its next stage. So a signal is *recorded*
here as well as raised; the IPOPT iteration callback asks IPOPT to stop while one is pending
(:func:`stop_requested`), and :meth:`sphere_nlp.nlp.AngleNLP.solve` raises it again once IPOPT has
returned (:func:`raise_if_interrupted`).

The same iteration callback enforces a run's deadline (:func:`deadline`): every IPOPT stage stops at
its first iteration past it, so ``max_time`` bounds the whole run, not each stage.

Example
-------
>>> with handled_signals():
...     raise_if_interrupted()          # nothing pending: returns
"""

import math
import signal
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


def _handler(signum, frame):
    global _pending
    if _pending is None:
        _pending = signum
    if not _deferred:
        raise Interrupted(signum)


def pending_signal():
    """The signal number recorded since :func:`handled_signals` began, or None."""
    return _pending


def raise_if_interrupted():
    """Raise :class:`Interrupted` if a signal has been recorded."""
    if _pending is not None:
        raise Interrupted(_pending)


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

    The previous handlers come back afterwards, and the record is cleared on entry. Inside another
    such block this one changes nothing. With ``only_default``, a signal whose handler is not
    Python's default (a program's own SIGINT handler) is left alone.
    """
    global _pending
    if (threading.current_thread() is not threading.main_thread()
            or signal.getsignal(signal.SIGINT) is _handler):
        yield
        return
    global _deferred, _committed
    _pending, saved, _committed = None, _deferred, False
    defaults = {signal.SIGINT: signal.default_int_handler, signal.SIGTERM: signal.SIG_DFL}
    previous = {}
    try:
        for s in signals:
            if not only_default or signal.getsignal(s) is defaults.get(s):
                previous[s] = signal.signal(s, _handler)
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
        _deferred, _committed = saved, False


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
