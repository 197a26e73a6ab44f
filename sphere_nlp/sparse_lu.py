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
import pymetis
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
    """A SuperLU factorisation whose solves refuse a non-finite right-hand side or result.

    With ``perm`` (new -> old index) the factorisation is of the permuted matrix P A P^T, and solves
    permute the right-hand side and the solution back, so they solve A x = rhs all the same.
    """

    def __init__(self, lu, perm=None):
        self.lu = lu
        self.perm = perm
        self.shape = lu.shape

    def solve(self, rhs):
        rhs = np.asarray(rhs, dtype=float)
        check_finite(rhs, "a right-hand side")
        if self.perm is None:
            x = self.lu.solve(rhs)
        else:
            x = np.empty_like(rhs)
            x[self.perm] = self.lu.solve(rhs[self.perm])
        check_finite(x, "a solution")
        return x

    __call__ = solve


# From this many unknowns a Laplacian-like solve is ordered by the mesh's nested dissection
# (``Connectivity.vertex_order``, computed once a mesh) restricted to its unknowns: the cotangent
# Laplacian of the Loop armadillo (173k vertices) factorises in 0.45 s against 1.27 s with SuperLU's
# own order (L+U 10.3M nonzeros against 18.6M, so solves are faster too); 0.13 against 0.29 s at 50k
# (nefertiti), 0.03 against 0.06 s at 15k; below ~10k either takes a few hundredths of a second.
NESTED_DISSECTION_UNKNOWNS = 10_000


def restricted_order(order, keep, minimum=None):
    """A nested-dissection ``order`` of all unknowns (new -> old) restricted to those with ``keep``
    (a boolean mask), in the kept unknowns' own numbering; None when ``order`` is None or fewer than
    ``minimum`` (default NESTED_DISSECTION_UNKNOWNS) are kept: SuperLU's own ordering is as good there.

    >>> restricted_order(np.array([3, 0, 2, 1]), np.array([True, False, True, True]), minimum=0).tolist()
    [2, 0, 1]
    """
    keep = np.asarray(keep, bool)
    if order is None or np.count_nonzero(keep) < (NESTED_DISSECTION_UNKNOWNS if minimum is None else minimum):
        return None
    order = np.asarray(order, dtype=np.intp)
    return (np.cumsum(keep) - 1)[order[keep[order]]]


def nested_dissection(graph):
    """METIS nested-dissection order (new -> old index) of the vertices of a sparsity pattern.

    ``graph`` is any square sparse matrix; its pattern is symmetrised and its diagonal ignored
    (METIS takes a graph without self loops).

    Examples
    --------
    >>> path = sp.diags([np.ones(4), np.ones(4)], [-1, 1], shape=(5, 5))
    >>> sorted(nested_dissection(path).tolist())
    [0, 1, 2, 3, 4]
    """
    G = sp.coo_matrix(graph)
    n = G.shape[0]
    off = (G.row != G.col) & (G.data != 0)
    rows, cols = G.row[off], G.col[off]
    if n < 3 or not len(rows):
        return np.arange(n)
    G = sp.csr_matrix((np.ones(2 * len(rows), np.int32), (np.r_[rows, cols], np.r_[cols, rows])), shape=(n, n))
    G.sort_indices()
    perm, _ = pymetis.nested_dissection(pymetis.CSRAdjacency(G.indptr, G.indices))
    return np.asarray(perm, dtype=np.intp)


def factorize(A, ordering=None, **options):
    """``scipy.sparse.linalg.splu(A, **options)`` after checking that A is finite; a :class:`CheckedLU`.

    ``ordering`` pre-orders a structurally symmetric A as P A P^T before SuperLU sees it: ``"metis"``
    (:func:`nested_dissection` of A's pattern) or a permutation (new -> old index), e.g. one computed
    once for several factorisations of a pattern; SuperLU's ``permc_spec`` then defaults to
    ``"NATURAL"`` (the order is taken as given). Nested dissection fills less than SuperLU's
    minimum-degree orderings on large meshes (the unfold's normal matrix at 173k vertices: 41M
    nonzeros instead of 51M, SuperLU 2.3x faster, 1.5x with METIS's own 0.9 s), but costs more
    than it saves below ~20k unknowns. Solves take and return vectors in A's own order.

    Raises :class:`NonFiniteSystem` for a non-finite A, and SuperLU's RuntimeError for a singular one.
    """
    A = sp.csc_matrix(A)
    check_finite(A.data)
    if ordering is None:
        return CheckedLU(spla.splu(A, **options))
    if isinstance(ordering, str):
        if ordering != "metis":
            raise ValueError(f"unknown ordering {ordering!r} (expected 'metis' or a permutation)")
        perm = nested_dissection(A)
    else:
        perm = np.asarray(ordering, dtype=np.intp)
        if perm.shape != (A.shape[0],) or not np.array_equal(np.sort(perm), np.arange(A.shape[0])):
            raise ValueError("ordering is not a permutation of the matrix's rows")
    options.setdefault("permc_spec", "NATURAL")
    return CheckedLU(spla.splu(sp.csc_matrix(A[perm][:, perm]), **options), perm)


def solve(A, rhs, **options):
    """Solve A x = rhs (rhs (n,) or (n, k)) through :func:`factorize`."""
    return factorize(A, **options).solve(rhs)
