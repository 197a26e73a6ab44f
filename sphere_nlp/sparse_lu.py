"""Sparse LU factorisations that refuse non-finite systems.

SuperLU (scipy.sparse.linalg.splu) factorises a matrix with NaN or inf entries without complaint,
and the BLAS under it then prints "** On entry to DTRSV parameter number 6 had an illegal value"
straight to the process's standard output and returns garbage. Every sparse solve of the pipeline
(the conformal start, the embeddings, the untangling, the authalic stage, the unfold) goes through
:func:`factorize`, which checks its input first, so a NaN upstream becomes an exception its caller
handles with a fall-back, never text on the terminal.

Examples
--------
>>> import scipy.sparse as sp
>>> lu = factorize(sp.csc_matrix([[2.0, 0.0], [0.0, 4.0]]))
>>> lu.solve(np.array([2.0, 2.0])).tolist()
[1.0, 0.5]
>>> factorize(sp.csc_matrix([[np.nan, 0.0], [0.0, 1.0]]))
Traceback (most recent call last):
...
sphere_nlp.sparse_lu.NonFiniteSystem: a linear system has 1 non-finite entries
"""

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla


class NonFiniteSystem(RuntimeError):
    """A linear system (matrix or right-hand side) with NaN or inf entries.

    A RuntimeError, as SuperLU's own "matrix is singular": the callers that fall back on a singular
    factorisation fall back on this too.
    """


def check_finite(values, what="a linear system"):
    """Raise :class:`NonFiniteSystem` unless every entry of ``values`` is finite."""
    bad = np.size(values) - np.count_nonzero(np.isfinite(values))
    if bad:
        raise NonFiniteSystem(f"{what} has {bad} non-finite entries")


class CheckedLU:
    """A SuperLU factorisation whose solves refuse a non-finite right-hand side or result."""

    def __init__(self, lu):
        self.lu = lu
        self.shape = lu.shape

    def solve(self, rhs):
        rhs = np.asarray(rhs, dtype=float)
        check_finite(rhs, "a right-hand side")
        x = self.lu.solve(rhs)
        check_finite(x, "a solution")
        return x

    __call__ = solve


def factorize(A, **options):
    """``scipy.sparse.linalg.splu(A, **options)`` after checking that A is finite; a :class:`CheckedLU`.

    Raises :class:`NonFiniteSystem` for a non-finite A, and SuperLU's RuntimeError for a singular one.
    """
    A = sp.csc_matrix(A)
    check_finite(A.data)
    return CheckedLU(spla.splu(A, **options))


def solve(A, rhs, **options):
    """Solve A x = rhs (rhs (n,) or (n, k)) through :func:`factorize`."""
    return factorize(A, **options).solve(rhs)
