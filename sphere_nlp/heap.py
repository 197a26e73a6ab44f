"""Keep the solver's large arrays on glibc's heap while it runs.

Every IPOPT iteration allocates and frees the same large blocks: MUMPS's factors at each
factorization, numpy's temporaries at each evaluation. glibc serves a block above its mmap
threshold (at most 32 MiB) with a fresh mmap and returns it on free, so the same pages fault in
again every iteration: hand_closed.obj original-areas spent 16 of its 110 s in the kernel, and
ran in 88 s with mmap off and freed memory kept (bunny.off 18-19 s against 14-16 s; the same
iterations and optimum; peak memory 4-18% higher on the benchmark rows). Under Dask's nanny,
which pins the trim threshold at 64 KiB, even blocks of 128 KiB were mapped afresh.

:func:`arrays_on_heap` sets glibc's ``mallopt`` for the duration of a solve and restores the
defaults after it, handing freed memory back to the system (``malloc_trim``). The settings are
process-wide, so concurrent solves in one process share them (a count decides when to restore).
Elsewhere than glibc it does nothing.
"""

import contextlib
import ctypes
import threading

# glibc's mallopt parameters (malloc.h) and their defaults.
M_TRIM_THRESHOLD, M_MMAP_MAX = -1, -4
DEFAULT_TRIM_THRESHOLD, DEFAULT_MMAP_MAX = 128 * 1024, 65536
# Freed memory below this much at the heap's top stays for the next iteration (mallopt takes an int).
SOLVE_TRIM_THRESHOLD = 2 ** 31 - 1

_lock = threading.Lock()
_active = 0             # solves inside arrays_on_heap now
_applied = False        # whether the outermost one's settings took effect


def _glibc():
    """glibc's ``libc.so.6`` with ``mallopt`` and ``malloc_trim``, or None elsewhere."""
    try:
        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt, libc.malloc_trim       # noqa: B018 (AttributeError if not glibc)
        return libc
    except (OSError, AttributeError):
        return None


def set_heap_only(libc):
    """Serve every allocation from the heap and keep freed memory; True if glibc accepted both."""
    return bool(libc.mallopt(M_MMAP_MAX, 0) and libc.mallopt(M_TRIM_THRESHOLD, SOLVE_TRIM_THRESHOLD))


@contextlib.contextmanager
def arrays_on_heap():
    """Context in which large allocations come from glibc's heap and stay there (module docstring).

    Yields True if the settings took effect (glibc), else False.

    Examples
    --------
    >>> import numpy as np
    >>> with arrays_on_heap():
    ...     float(np.ones(10 ** 6).sum())
    1000000.0
    """
    global _active, _applied
    libc = _glibc()
    if libc is None:
        yield False
        return
    with _lock:
        _active += 1
        if _active == 1:
            _applied = set_heap_only(libc)
    try:
        yield _applied
    finally:
        with _lock:
            _active -= 1
            if _active == 0:
                libc.mallopt(M_MMAP_MAX, DEFAULT_MMAP_MAX)
                libc.mallopt(M_TRIM_THRESHOLD, DEFAULT_TRIM_THRESHOLD)
                libc.malloc_trim(0)
