"""The angle NLP of Sheffer, Gotsman & Dyn (2004), built symbolically in CasADi and solved by IPOPT.

This is the only module that imports CasADi. Two formulations of the same problem are available:

``faithful``
    The paper as written: unknowns alpha (3t) and e (t); equality constraints (6) triangle
    sums, (7) vertex sums, (8) edge consistency through the spherical cosine rule; inequalities
    (3) alpha > 0, (4) e > 0, (5) e < 2 alpha. It is the reference the fast path is tested against.
``substituted``
    (6) is solved exactly for e = alpha0 + alpha1 + alpha2 - pi and substituted everywhere, leaving
    3t unknowns, constraints (7) and (8), and the inequalities (3)-(5) as linear constraints in alpha.
    Same feasible set, same objective, same optimum; fewer unknowns and constraints.

``log-chord`` (default)
    Unknowns p = log u and s = log e, where u_j = alpha_j - e/2. Every p and s gives u, e > 0, and
    u > 0 is exactly e < 2 alpha, so (3)-(5) hold strictly at every iterate without being
    constraints. (6) is sum(u) + e/2 = pi, (7) sums u + e/2, and (8) compares the log half-chords
    log sin^2(a/2) = log sin(e/2) + log sin u_j - log sin alpha_k - log sin alpha_l, the half-angle
    form of the cosine rule: it measures relative edge-length mismatch, so it is equally accurate for
    triangles of any size, and excesses can move over many orders of magnitude by additive steps.
    At obtuse corners sin alpha and sin u are taken through the other two corners (see
    ``obtuse_corners``).

The log-chord form hands IPOPT exact derivatives assembled from its per-triangle structure
(``_log_chord_parts``): CasADi's generic differentiation of the whole graph spent superlinear time in
sparsity detection (10 s of set-up at 10,242 vertices, 0.4 s now). CasADi derives the per-triangle
functions symbolically; by default (``evaluation="numpy"``) IPOPT's callbacks replay them on whole
arrays in numpy (``_vectorize``, ``_LogChordValues``), which cut the function evaluations of a
86k-triangle solve from 7.6 s to 2.1 s; ``evaluation="casadi"`` maps them over the triangles in a
CasADi graph instead, the reference. Tests check both against CasADi's automatic differentiation.
The area modes hand IPOPT a modified Hessian (``hessian="clipped"``: the exact one less the negative
part of the term the log unknowns add, which vanishes at the optima; see :class:`LogChordNLP`).

The paper's two forms are :class:`PaperNLP`, the log-chord form :class:`LogChordNLP`; both share
:class:`_AngleProblem`'s evaluation, bounds and IPOPT runs, and :func:`AngleNLP` builds either from
a formulation's name. The faithful and substituted forms keep (8) in the paper's quotient form, so
the Lagrangian Hessian stays block-diagonal per triangle (multiplying it out couples the two
triangles of every edge and is much slower).
"""

import contextlib
import io
import os
import sys
import time
from dataclasses import dataclass

import casadi as ca
import numpy as np
import scipy.sparse as sp

from . import interrupts
from .names import DEFAULT_FORMULATION, FORMULATIONS  # noqa: F401  (defined there for a light --help)
from .settings import DEFAULT_SETTINGS

# How the log-chord form is evaluated for IPOPT: "numpy" (vectorised over triangles, see
# _LogChordValues) or "casadi" (the same functions mapped in CasADi's interpreter; the reference).
EVALUATIONS = ("numpy", "casadi")
# The Hessian handed to IPOPT by the log-chord form (see AngleNLP's ``hessian``).
HESSIANS = ("exact", "clipped", "clipped-corners")

# What the return status of a run means, the one table of them: "solved" (a result), "limit"
# (stopped short by the caller's max_iter or max_time; its iterate can still be projected onto the
# constraints), "diverged" (stopped by the divergence watch, see AngleNLP.solve); any other status
# (IPOPT's failures, LINEAR_SOLVER_FAILED: stopped when the BLAS under MUMPS complained, and
# LINEAR_SOLVER_OUT_OF_MEMORY: failed after MUMPS could not get its memory) is "failed".
STATUS_KINDS = {
    "Solve_Succeeded": "solved",
    "Solved_To_Acceptable_Level": "solved",
    "Maximum_Iterations_Exceeded": "limit",
    "Maximum_WallTime_Exceeded": "limit",
    "Maximum_CpuTime_Exceeded": "limit",
    "Diverged": "diverged",
}


def status_kind(status):
    """"solved", "limit", "diverged" or "failed" (see :data:`STATUS_KINDS`).

    >>> status_kind("Solved_To_Acceptable_Level"), status_kind("Restoration_Failed")
    ('solved', 'failed')
    """
    return STATUS_KINDS.get(status, "failed")


@dataclass
class Iterate:
    """One IPOPT iterate, kept by a run that watches for divergence (``IpoptRun.best_sound``)."""

    x: np.ndarray
    lam_g: np.ndarray
    lam_x: np.ndarray
    iteration: int
    objective: float
    violation: float


@dataclass
class IpoptRun:
    """The outcome of one IPOPT run (:meth:`AngleNLP.solve`).

    Attributes
    ----------
    x0 : array
        Where the run started.
    x : array
        Where it ended (IPOPT's last iterate).
    lam_g, lam_x : arrays
        Constraint and bound multipliers there.
    objective : float
    status : str
        IPOPT's return status, "Diverged" (see :data:`STATUS_KINDS`), or "Linear_Solver_Failed"
        (the linear algebra under IPOPT printed a complaint, :data:`LINEAR_ALGEBRA_COMPLAINTS`: the
        run stops at its next iteration, and the text is not shown), or "Linear_Solver_Out_Of_Memory"
        (a failed run during which MUMPS could not get the memory to factorise,
        :data:`OUT_OF_MEMORY_COMPLAINTS`; :func:`failure_advice` says what to do).
    iterations : int
    time_s, build_s : float
        Seconds in IPOPT, and in building the solver before it (for an NLP's first run, also in
        building the NLP's numeric evaluators).
    stats : dict
        IPOPT's statistics of the run (CasADi's ``solver.stats()``: per-iteration regularization
        sizes, timings, ...).
    touched : bool
        Whether the run ended on its window on the log excesses (set by the caller that bounds them,
        :func:`sphere_nlp.solve.windowed_solve`).
    best_sound : Iterate or None
        A run that watched for divergence (``abort_violation``): its iterate of least objective among
        those within ``sound_violation`` of the constraints, where a diverged run can resume.
    """

    x0: np.ndarray
    x: np.ndarray
    lam_g: np.ndarray
    lam_x: np.ndarray
    objective: float
    status: str
    iterations: int
    time_s: float = 0.0
    build_s: float = 0.0
    stats: dict = None
    touched: bool = False
    best_sound: Iterate = None

    @property
    def success(self):
        """Whether IPOPT reports a solution (not yet whether it is feasible to the solver's tolerance)."""
        return status_kind(self.status) == "solved"

    @property
    def stopped_by_limit(self):
        """Whether the caller's iteration or time limit stopped the run."""
        return status_kind(self.status) == "limit"

    @property
    def finite(self):
        """Whether the end point is finite."""
        return bool(np.isfinite(self.x).all())


def check_ipopt_options(options):
    """Raise ValueError naming the first IPOPT option IPOPT rejects (unknown name, wrong type or value).

    IPOPT is asked on a one-variable problem, with its complaint (an option dump on stdout) silenced,
    so that a bad option is a usage error before any mesh is solved.

    Example
    -------
    >>> check_ipopt_options({"tol": 1e-9})
    >>> check_ipopt_options({"bogus_option": 1})
    Traceback (most recent call last):
    ...
    ValueError: IPOPT rejects option bogus_option=1 (no such option)
    """
    x = ca.SX.sym("x")
    for name, value in dict(options).items():
        if not isinstance(name, str):
            raise ValueError("IPOPT option names are strings, not %r" % (name,))
        try:
            with _stdout_silenced():
                ca.nlpsol("check", "ipopt", {"x": x, "f": x * x},
                          {"print_time": False, "ipopt": {name: value, "print_level": 0, "sb": "yes"}})
        except (RuntimeError, TypeError, NotImplementedError) as exc:
            text = str(exc)
            reason = ("no such option" if "No such IPOPT option" in text else
                      "wrong type" if "type mismatch" in text else "invalid value")
            raise ValueError("IPOPT rejects option %s=%r (%s)" % (name, value, reason)) from None


@contextlib.contextmanager
def _stdout_silenced():
    """Send standard output (where IPOPT and CasADi print) to /dev/null inside the block."""
    sys.stdout.flush()
    saved = os.dup(1)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 1)
            # CasADi's Python build prints through sys.stdout, IPOPT's own journal through fd 1.
            with contextlib.redirect_stdout(null):
                yield
    finally:
        _flush_c_stdio()                    # IPOPT's buffered text goes to /dev/null, not later to stdout
        os.dup2(saved, 1)
        os.close(saved)


# What the BLAS under MUMPS (CasADi's bundled OpenBLAS) prints, to the C standard output, when
# MUMPS hands it a matrix of impossible dimensions ("** On entry to DTRSV parameter number 6 had
# an illegal value"; it then returns without computing, and IPOPT goes on with a wrong step).
LINEAR_ALGEBRA_COMPLAINTS = (b"had an illegal value",)
# The status of a run stopped because the linear algebra under IPOPT complained.
LINEAR_SOLVER_FAILED = "Linear_Solver_Failed"

# What IPOPT prints (at print_level 1 and up, to the C standard output) when MUMPS cannot get the
# memory a factorisation needs: INFO(1) = -13 (an allocation refused: "MUMPS returned INFO(1) =-13
# - out of memory when trying to allocate 4225 MB." and a hint about mumps_mem_percent), or -8/-9
# still after IPOPT's retries with more workspace ("MUMPS was not able to obtain enough memory."),
# and the symbolic phase's "Error=-13 returned from MUMPS". IPOPT then only sees a failed step and
# ends as Restoration_Failed (the 692k-vertex armadillo before MUMPS's reservation was cut), which
# says nothing of memory. MUMPS's other error returns are IPOPT's to handle.
OUT_OF_MEMORY_COMPLAINTS = (b"out of memory when trying to allocate", b"was not able to obtain enough memory",
                            b"Error=-13 returned from MUMPS", b"Error=-9 returned from MUMPS",
                            b"Error=-8 returned from MUMPS")
# The line IPOPT prints after the -13 one; part of the same message, so not shown either.
_OUT_OF_MEMORY_HINT = b'helps to decrease the value of the option "mumps_mem_percent"'
# The status of a failed run during which MUMPS ran out of memory (a run that recovered keeps its own).
LINEAR_SOLVER_OUT_OF_MEMORY = "Linear_Solver_Out_Of_Memory"

# What a user can do about a status, for the failure line.
STATUS_ADVICE = {
    LINEAR_SOLVER_OUT_OF_MEMORY: ("the linear solver (MUMPS) ran out of memory factorising IPOPT's "
                                  "system: free memory (close other programs, run one large mesh at "
                                  "a time), use a machine with more, or solve a decimated mesh"),
}


def classify_c_output(text):
    """What the captured C output of an IPOPT run says went wrong in the linear algebra under it:
    :data:`LINEAR_SOLVER_FAILED` (the BLAS refused its arguments, :data:`LINEAR_ALGEBRA_COMPLAINTS`),
    :data:`LINEAR_SOLVER_OUT_OF_MEMORY` (MUMPS could not get memory, :data:`OUT_OF_MEMORY_COMPLAINTS`)
    or None. A refused BLAS call counts first: its steps are wrong whatever the memory.

    Examples
    --------
    >>> classify_c_output(b"MUMPS returned INFO(1) =-13 - out of memory when trying to allocate 4225 MB.\\n")
    'Linear_Solver_Out_Of_Memory'
    >>> classify_c_output(b" ** On entry to DTRSV parameter number  6 had an illegal value\\n")
    'Linear_Solver_Failed'
    >>> classify_c_output(b"iter    objective    inf_pr\\n") is None
    True
    """
    text = text.encode() if isinstance(text, str) else bytes(text)
    if any(c in text for c in LINEAR_ALGEBRA_COMPLAINTS):
        return LINEAR_SOLVER_FAILED
    if any(c in text for c in OUT_OF_MEMORY_COMPLAINTS):
        return LINEAR_SOLVER_OUT_OF_MEMORY
    return None


def failure_advice(status):
    """A status's advice to the user (:data:`STATUS_ADVICE`), or None.

    >>> failure_advice("Linear_Solver_Out_Of_Memory").startswith("the linear solver (MUMPS) ran out of memory")
    True
    >>> failure_advice("Restoration_Failed") is None
    True
    """
    return STATUS_ADVICE.get(status)


def _shown(line):
    """Whether a line of captured C output goes on to the terminal: not the complaints and memory
    failures :func:`classify_c_output` turns into a status."""
    return classify_c_output(line) is None and _OUT_OF_MEMORY_HINT not in line


class _ScannedStdout(io.TextIOBase):
    """Python's standard output during an IPOPT run: CasADi hands IPOPT's text (its errors, among
    them MUMPS's out-of-memory lines, :data:`OUT_OF_MEMORY_COMPLAINTS`) to ``sys.stdout``, not to
    fd 1. Whole lines that :func:`classify_c_output` classifies are kept back and recorded in
    ``complaints``; everything else goes on to ``target``."""

    def __init__(self, target):
        self.target, self.complaints, self._partial = target, [], ""

    def writable(self):
        return True

    def write(self, text):
        lines = (self._partial + text).splitlines(keepends=True)
        self._partial = lines.pop() if lines and not lines[-1].endswith(("\n", "\r")) else ""
        for line in lines:
            complaint = classify_c_output(line)
            if complaint is not None:
                self.complaints.append(complaint)
            elif _shown(line.encode(errors="replace")):
                self.target.write(line)
        return len(text)

    def flush(self):
        if self._partial:
            self.target.write(self._partial)
            self._partial = ""
        self.target.flush()


class _CapturedOutput:
    """What :func:`_c_stdout_captured` yields: the file fd 1 goes to (``sink``) and Python's
    scanned standard output (``python``), read by :func:`_complained`."""

    def __init__(self, sink, python):
        self.sink, self.python = sink, python


@contextlib.contextmanager
def _c_stdout_captured():
    """Inside the block, what C code writes to the standard output (fd 1) goes to a temporary file,
    and Python's standard output (where CasADi sends IPOPT's own text) through a filter; both are
    yielded (:class:`_CapturedOutput`): the linear algebra under IPOPT prints its complaints there
    and IPOPT its memory failures, which the iteration callback reads (:func:`classify_c_output`)
    and the terminal never shows. The rest of the C text is written to the standard output after
    the block; Python's ``print`` (and IPOPT's log, if asked for) still reaches it as it happens."""
    import tempfile

    try:
        python_on_fd1 = sys.stdout.fileno() == 1
    except (AttributeError, OSError, ValueError):     # a notebook's or a test's capture
        python_on_fd1 = False
    sys.stdout.flush()
    _flush_c_stdio()
    saved = os.dup(1)
    with tempfile.TemporaryFile() as sink, open(saved, "w", closefd=False) as real_stdout:
        os.dup2(sink.fileno(), 1)
        python = _ScannedStdout(real_stdout if python_on_fd1 else sys.stdout)
        try:
            with contextlib.redirect_stdout(python):
                yield _CapturedOutput(sink, python)
                python.flush()
        finally:
            _flush_c_stdio()
            os.dup2(saved, 1)
            sink.seek(0)
            kept = [line for line in sink.read().splitlines(keepends=True) if _shown(line)]
            if kept:
                os.write(saved, b"".join(kept))
            os.close(saved)


def _complained(captured, position):
    """(:func:`classify_c_output` of the C output written to ``captured.sink`` after ``position``
    and of the Python-side lines kept back since the last call, the new position)."""
    _flush_c_stdio()
    complaints, captured.python.complaints = captured.python.complaints, []
    size = os.fstat(captured.sink.fileno()).st_size
    if size > position:
        complaints.append(classify_c_output(os.pread(captured.sink.fileno(), size - position, position)))
    else:
        size = position
    if LINEAR_SOLVER_FAILED in complaints:
        return LINEAR_SOLVER_FAILED, size
    return (LINEAR_SOLVER_OUT_OF_MEMORY if LINEAR_SOLVER_OUT_OF_MEMORY in complaints else None), size


def _flush_c_stdio():
    try:
        import ctypes

        ctypes.CDLL(None).fflush(None)
    except (OSError, AttributeError):
        pass


def _sparse_dm(matrix):
    """scipy.sparse matrix -> CasADi DM with the same sparsity."""
    csc = matrix.tocsc()
    csc.sort_indices()
    sparsity = ca.Sparsity(csc.shape[0], csc.shape[1], csc.indptr.tolist(), csc.indices.tolist())
    return ca.DM(sparsity, csc.data)


def _mx_from_triplets(rows, cols, values, n_rows, n_cols):
    """Sparse MX with entries ``values[k]`` at (rows[k], cols[k]) (no duplicates), any order."""
    order = np.lexsort((rows, cols))                      # CasADi stores nonzeros column by column
    sparsity = ca.Sparsity.triplet(n_rows, n_cols, rows[order].tolist(), cols[order].tolist())
    return ca.MX(sparsity, values[order.tolist()])


def edge_cosines_sx(alpha, prev_idx, next_idx):
    """Cosine of the arc opposite every corner, by the spherical cosine rule (symbolic).

    cos a = (cos A + cos B cos C) / (sin B sin C), with A the corner, B and C the other two.
    """
    cos_a, sin_a = ca.cos(alpha), ca.sin(alpha)
    return (cos_a + cos_a[prev_idx] * cos_a[next_idx]) / (sin_a[prev_idx] * sin_a[next_idx])


class _ProgressCallback(ca.Callback):
    """IPOPT iteration callback: reports (iteration, objective, violation, elapsed) to a function, and
    stops the run once it has diverged.

    A run counts as diverged when its max constraint violation has stayed above
    ``self.abort_violation`` for ``self.abort_iterations`` iterations in a row (see
    :meth:`AngleNLP.solve`); IPOPT then ends with User_Requested_Stop at that iterate. Such a run
    also keeps its best iterate within ``self.sound_violation`` of the constraints (``self.best``).
    """

    def __init__(self, n_x, n_g, lbg, ubg):
        ca.Callback.__init__(self)
        self._n_x, self._n_g = n_x, n_g
        self._lbg, self._ubg = lbg, ubg
        self.reset(None, None, 0)
        self.construct("sphere_nlp_progress", {})

    def reset(self, report, abort_violation, abort_iterations, on_iterate=None, sound_violation=0.0):
        """Start a run: report to ``report`` (or nobody), watch for divergence if abort_violation
        (keeping the best iterate within ``sound_violation``), hand every iterate to ``on_iterate``
        (if given)."""
        self._report, self._on_iterate = report, on_iterate
        self.iteration = 0
        self.start = time.perf_counter()
        self.abort_violation, self.abort_iterations = abort_violation, abort_iterations
        self.sound_violation = sound_violation
        self.iterations_above = 0
        self.aborted = False
        self.best = None
        # The file C's standard output goes to during the run (_c_stdout_captured), how much of it
        # has been read, and whether it showed a linear-algebra complaint.
        self.c_output, self.c_output_read = None, 0
        self.linear_solver_failed = self.out_of_memory = False

    def get_n_in(self):
        return ca.nlpsol_n_out()

    def get_n_out(self):
        return 1

    def get_name_in(self, i):
        return ca.nlpsol_out(i)

    def get_name_out(self, i):
        return "ret"

    def get_sparsity_in(self, i):
        name = ca.nlpsol_out(i)
        if name == "f":
            return ca.Sparsity.scalar()
        if name in ("x", "lam_x"):
            return ca.Sparsity.dense(self._n_x)
        if name in ("g", "lam_g"):
            return ca.Sparsity.dense(self._n_g)
        return ca.Sparsity(0, 0)

    def has_eval_buffer(self):
        return True

    def eval_buffer(self, arg, res):
        # Buffers, not DMs: CasADi's DM-to-numpy conversion goes through a Python list (docs/design.md,
        # "Large meshes"). The buffers are CasADi's, so whatever is kept is copied.
        values = dict(zip(ca.nlpsol_out(), arg))

        def vector(name):
            return np.empty(0) if values[name] is None else np.frombuffer(values[name], dtype=float)
        stop = self._on_iteration(vector)
        if res[0] is not None:
            np.frombuffer(res[0], dtype=float)[:] = stop
        return 0

    def _on_iteration(self, vector):
        """Report, keep the best sound iterate, and say whether IPOPT must stop (1) or go on (0)."""
        g = vector("g")
        violation = float(np.max(np.maximum(self._lbg - g, g - self._ubg), initial=0.0))
        objective = float(vector("f")[0])
        if self._report is not None:
            self._report(self.iteration, objective, violation, time.perf_counter() - self.start)
        if self._on_iterate is not None:
            self._on_iterate(self.iteration, *[vector(k).copy() for k in ("x", "lam_g", "lam_x")], objective)
        if (self.abort_violation is not None and violation <= self.sound_violation
                and (self.best is None or objective < self.best.objective)):
            self.best = Iterate(*[vector(k).copy() for k in ("x", "lam_g", "lam_x")],
                                iteration=self.iteration, objective=objective, violation=violation)
        self.iteration += 1
        # not (violation <= ...) so that a NaN violation counts as above
        above = self.abort_violation is not None and not violation <= self.abort_violation
        self.iterations_above = self.iterations_above + 1 if above else 0
        if self.abort_violation is not None and self.iterations_above >= self.abort_iterations:
            self.aborted = True
            return 1                        # non-zero asks IPOPT to stop
        if interrupts.stop_requested():     # a signal, or the run's deadline (see interrupts)
            return 1
        if self.c_output is not None and self.read_complaints():
            return 1
        return 0

    def read_complaints(self):
        """Read the captured output written since the last read (:func:`_complained`) and record
        what it says; True if the linear algebra failed, so that the run must stop."""
        complaint, self.c_output_read = _complained(self.c_output, self.c_output_read)
        if complaint == LINEAR_SOLVER_OUT_OF_MEMORY:
            # IPOPT may yet recover (a later factorisation that fits): the run goes on, and its
            # status says out of memory only if it fails.
            self.out_of_memory = True
        elif complaint is not None:
            self.linear_solver_failed = True
        return self.linear_solver_failed


# numpy expressions for the operations CasADi's SX virtual machine can hold (see _vectorize)
_UNARY_OPERATIONS = {
    ca.OP_ASSIGN: "{0}", ca.OP_NEG: "-{0}", ca.OP_EXP: "np.exp({0})", ca.OP_LOG: "np.log({0})",
    ca.OP_SIN: "np.sin({0})", ca.OP_COS: "np.cos({0})", ca.OP_TAN: "np.tan({0})",
    ca.OP_SQRT: "np.sqrt({0})", ca.OP_SQ: "{0} * {0}", ca.OP_TWICE: "2.0 * {0}",
    ca.OP_INV: "1.0 / {0}", ca.OP_FABS: "np.abs({0})", ca.OP_SIGN: "np.sign({0})",
    ca.OP_ASIN: "np.arcsin({0})", ca.OP_ACOS: "np.arccos({0})", ca.OP_ATAN: "np.arctan({0})",
    ca.OP_SINH: "np.sinh({0})", ca.OP_COSH: "np.cosh({0})", ca.OP_TANH: "np.tanh({0})",
    ca.OP_EXPM1: "np.expm1({0})", ca.OP_LOG1P: "np.log1p({0})",
}
_BINARY_OPERATIONS = {
    ca.OP_ADD: "{0} + {1}", ca.OP_SUB: "{0} - {1}", ca.OP_MUL: "{0} * {1}", ca.OP_DIV: "{0} / {1}",
    ca.OP_POW: "np.power({0}, {1})", ca.OP_CONSTPOW: "np.power({0}, {1})",
    ca.OP_FMIN: "np.minimum({0}, {1})", ca.OP_FMAX: "np.maximum({0}, {1})",
    ca.OP_ATAN2: "np.arctan2({0}, {1})", ca.OP_HYPOT: "np.hypot({0}, {1})",
    ca.OP_IF_ELSE_ZERO: "np.where({0} != 0, {1}, 0.0)",
}


# Triangles per slice in _vectorize's evaluation (see there).
_VECTOR_SLICE = 8192


def _vectorize(function):
    """A numpy version of a small SX Function, evaluated for a whole batch at once.

    The returned callable takes one array per input, shaped (input nonzeros, batch), and returns one
    array per output, shaped (output nonzeros, batch). It replays the Function's own instruction
    list (so it computes exactly what CasADi computes) on arrays instead of scalars: CasADi's
    ``map`` evaluates a per-triangle function one triangle at a time in its interpreter, which
    took 30% of a solve at 86k triangles; on whole arrays the same instructions run 3.5-6x faster.

    Examples
    --------
    >>> x = ca.SX.sym("x", 2)
    >>> f = _vectorize(ca.Function("f", [x], [ca.vertcat(ca.sin(x[0]) * x[1], 3.0)]))
    >>> f(np.array([[0.0, np.pi / 2], [2.0, 2.0]]))[0].tolist()
    [[0.0, 2.0], [3.0, 3.0]]
    """
    lines = ["def kernel(%s):" % ", ".join(["out"] + ["in%d" % k for k in range(function.n_in())])]
    for k in range(function.n_instructions()):
        op = function.instruction_id(k)
        arguments, results = function.instruction_input(k), function.instruction_output(k)
        if op == ca.OP_INPUT:
            lines.append("    w%d = in%d[%d]" % (results[0], arguments[0], arguments[1]))
        elif op == ca.OP_OUTPUT:
            lines.append("    out[%d][%d] = w%d" % (results[0], results[1], arguments[0]))
        elif op == ca.OP_CONST:
            lines.append("    w%d = %r" % (results[0], float(function.instruction_constant(k))))
        elif op in _UNARY_OPERATIONS:
            lines.append("    w%d = %s" % (results[0], _UNARY_OPERATIONS[op].format("w%d" % arguments[0])))
        elif op in _BINARY_OPERATIONS:
            lines.append("    w%d = %s" % (results[0], _BINARY_OPERATIONS[op].format(
                "w%d" % arguments[0], "w%d" % arguments[1])))
        else:
            raise NotImplementedError("operation %d in %s has no numpy form" % (op, function.name()))
    namespace = {"np": np}
    exec(compile("\n".join(lines), "<vectorized %s>" % function.name(), "exec"), namespace)
    kernel = namespace["kernel"]
    sizes = [function.nnz_out(k) for k in range(function.n_out())]

    def evaluate(*arrays):
        batch = np.shape(arrays[0])[-1]
        out = [np.empty((size, batch)) for size in sizes]
        with np.errstate(all="ignore"):          # NaN/inf propagate as in CasADi; IPOPT handles them
            # In slices of the batch: each instruction makes a temporary array, and at the whole
            # batch's size (2.8 MB at 346k triangles) every one was a fresh mmap and page faults
            # (a third of the evaluation time was system time); a slice's temporaries stay in cache.
            for begin in range(0, batch, _VECTOR_SLICE):
                part = slice(begin, begin + _VECTOR_SLICE)
                kernel([o[:, part] for o in out], *[a[..., part] for a in arrays])
        return out
    return evaluate


def entry_positions(pattern, rows, cols):
    """Index of each (rows[k], cols[k]) among the stored entries of the CSC matrix ``pattern``."""
    lookup = sp.csr_matrix((np.arange(1, pattern.nnz + 1, dtype=float), pattern.indices, pattern.indptr),
                           shape=pattern.shape[::-1]).T.tocsr()       # same entries, row-indexable
    index = np.asarray(lookup[rows, cols]).ravel().astype(np.int64) - 1
    if (index < 0).any():
        raise AssertionError("entry outside the sparsity pattern")
    return index


def _casadi_sparsity(csc):
    """CasADi Sparsity of a scipy CSC matrix with sorted indices."""
    return ca.Sparsity(csc.shape[0], csc.shape[1], csc.indptr.tolist(), csc.indices.tolist())


def _per_triangle_sparsity(touched):
    """CasADi Sparsity of the log-chord Jacobian: row r has all four unknowns of every triangle
    that ``touched`` (scipy CSC, rows x t, sorted indices) marks in row r.

    The unknowns are ordered (log u of triangle 0, 1, ...; log e of triangle 0, 1, ...), so the
    pattern is [touched (x) (1 1 1), touched], assembled in CasADi from ``touched`` alone: handing
    CasADi the whole pattern as Python lists took 1.5 s at 173k vertices, this 0.5 s.
    """
    by_triangle = _casadi_sparsity(touched)
    pattern = ca.kron(by_triangle, ca.Sparsity.dense(1, 3))
    pattern.appendColumns(by_triangle)
    return pattern


def _triangle_blocks_sparsity(t, extra_rows=(), extra_cols=()):
    """CasADi Sparsity of the upper triangles of the per-triangle 4x4 Hessian blocks (the
    unknowns ordered as in :func:`_per_triangle_sparsity`), united with the entries
    (``extra_rows``, ``extra_cols``), assembled in CasADi (see there)."""
    diagonal = ca.Sparsity.diag(t)
    angle_rows = ca.kron(diagonal, ca.Sparsity.upper(3))
    angle_rows.appendColumns(ca.kron(diagonal, ca.Sparsity.dense(3, 1)))
    excess_rows = ca.Sparsity(t, 3 * t)
    excess_rows.appendColumns(diagonal)
    pattern = ca.vertcat(angle_rows, excess_rows)
    if len(extra_rows):
        pattern = pattern.unite(ca.Sparsity.triplet(4 * t, 4 * t, np.asarray(extra_rows).tolist(),
                                                    np.asarray(extra_cols).tolist()))
    return pattern


# (row, column) of each stored entry of a triangle's 4x4 Hessian block: its upper triangle,
# column-major, the order of the per-triangle Hessian function's outputs.
BLOCK_UPPER_ENTRIES = [(i, j) for j in range(4) for i in range(j + 1)]


def nearest_semidefinite_blocks(upper_entries):
    """Each symmetric 4x4 matrix, given by its upper triangle, with its negative eigenvalues set to 0.

    The nearest positive semidefinite matrix in the Frobenius norm (Higham 1988), as used by
    projected Newton methods on per-element Hessians.

    Parameters
    ----------
    upper_entries : (10, k) array
        The upper triangles of k matrices, entries in the order of :data:`BLOCK_UPPER_ENTRIES`:
        (0,0), (0,1), (1,1), (0,2), (1,2), (2,2), (0,3), (1,3), (2,3), (3,3).

    Returns
    -------
    (10, k) array, the same layout.

    Examples
    --------
    >>> import numpy as np
    >>> upper = np.array([[1.0], [0.0], [-2.0], [0.0], [0.0], [3.0], [0.0], [0.0], [0.0], [0.0]])
    >>> nearest_semidefinite_blocks(upper).ravel().tolist()
    [1.0, 0.0, 0.0, 0.0, 0.0, 3.0, 0.0, 0.0, 0.0, 0.0]
    """
    rows, cols = np.array(BLOCK_UPPER_ENTRIES).T
    matrices = np.zeros((upper_entries.shape[1], 4, 4))
    matrices[:, rows, cols] = upper_entries.T
    matrices[:, cols, rows] = upper_entries.T
    eigenvalues, vectors = np.linalg.eigh(matrices)
    projected = np.einsum("kij,kj,klj->kil", vectors, np.maximum(eigenvalues, 0.0), vectors)
    return projected[:, rows, cols].T


class _LogChordValues:
    """The log-chord NLP's objective, constraints and exact derivatives, in numpy.

    The same quantities as the CasADi graph of :meth:`AngleNLP._log_chord_graph`, from the same
    per-triangle SX functions (replayed on arrays by :func:`_vectorize`), assembled with sparsity
    patterns fixed once here: jac g = A D has one product per entry (each row of A touches a
    triangle at most once), and the Hessian is the triangles' 4x4 blocks plus the dropped-vertex
    penalty's small dense term. The per-triangle values at the last x are cached, because IPOPT
    asks for f, g, grad f and jac g at the same point.
    """

    def __init__(self, parts):
        self._triangle = _vectorize(parts["triangle"])
        self._triangle_jacobian = _vectorize(parts["triangle_jacobian"])
        self._triangle_hessian = _vectorize(parts["triangle_hessian"])
        self._parameters = [np.ascontiguousarray(p, dtype=float) for p in parts["parameters"]]
        variable_of, upper, A, P = parts["variable_of"], parts["upper"], parts["A"], parts["P"]
        t = len(variable_of)
        self.n_faces, self.n_variables = t, 4 * t
        self._width = A.shape[1] // t
        self._A, self._At, self._b = A.tocsr(), A.T.tocsr(), parts["b"]
        self._objective_rows = parts["objective_rows"]
        self._P, self._penalty = (P.tocsr() if P is not None else None), parts["dropped_penalty"]
        width = self._width
        # D = dh/dx is kept as the per-triangle Jacobian returns it: (4 width, t), row c width + r
        # holding dh_r/dz_c of every triangle; entry (r, c, i) sits at flat index (c width + r) t + i.
        d_rows, d_cols = parts["d_rows"], parts["d_cols"]                  # triangle-major order
        flat_index = (np.arange(4 * width)[None, :] * t + np.arange(t)[:, None]).ravel()
        located = sp.csr_matrix((flat_index + 1.0, (d_rows, d_cols)), shape=(width * t, 4 * t))
        # jac g = A D: each entry is +-1 times one entry of D, because no row of A touches a
        # triangle twice; then each of A's entries (a row of D) gives 4 entries of its own.
        product = (self._A @ located).tocsc()
        product.sort_indices()
        if product.nnz != 4 * self._A.nnz:
            raise AssertionError("a row of A touches a triangle twice")
        self._jac_source = np.abs(product.data).astype(np.int64) - 1         # flat index into D
        self._jac_negative = np.flatnonzero(product.data < 0)
        A_rows = np.repeat(np.arange(self._A.shape[0]), np.diff(self._A.indptr))
        touched = sp.csc_matrix((np.ones(self._A.nnz), (A_rows, self._A.indices // width)),
                                shape=(self._A.shape[0], t))
        touched.sort_indices()
        self.jacobian_sparsity = _per_triangle_sparsity(touched)
        if self._P is not None:
            # The penalty needs P D on the unknowns of the triangles at the left-out vertices:
            # P (entries 1) picks alpha rows 8i + r, r = 2 + j, whose D entries are (r, c, i), c = 0..3.
            P_rows, P_cols = self._P.nonzero()
            tri_of, r_of = P_cols // width, P_cols % width
            variables = np.unique(variable_of[tri_of].ravel())
            self._penalty_rows = np.repeat(P_rows, 4)
            self._penalty_columns = np.searchsorted(variables, variable_of[tri_of].ravel())
            self._penalty_sources = ((np.arange(4)[None, :] * width + r_of[:, None]) * t + tri_of[:, None]).ravel()
            self._penalty_shape = (self._P.shape[0], len(variables))
        # Hessian (upper triangle): the 4x4 blocks, and the penalty's outer product on the
        # variables of the triangles at the left-out vertices.
        hu_rows = variable_of[:, [i for i, _ in upper]].ravel()
        hu_cols = variable_of[:, [j for _, j in upper]].ravel()
        rows, cols = [hu_rows], [hu_cols]
        if self._P is not None:
            a, c = np.triu_indices(len(variables))
            rows.append(variables[a])
            cols.append(variables[c])
            self._penalty_upper = (a, c)
        rows, cols = np.concatenate(rows), np.concatenate(cols)
        pattern = sp.csc_matrix((np.ones(len(rows)), (rows, cols)), shape=(4 * t, 4 * t))
        pattern.sum_duplicates()
        pattern.sort_indices()
        self.hessian_sparsity = _triangle_blocks_sparsity(t, rows[len(hu_rows):], cols[len(hu_cols):])
        if (self.hessian_sparsity.nnz(), self.jacobian_sparsity.nnz()) != (pattern.nnz, product.nnz):
            raise AssertionError("the unknowns are not laid out as the CasADi sparsities assume")
        self._hessian_nnz = pattern.nnz
        self._block_positions = entry_positions(pattern, hu_rows, hu_cols).reshape(t, len(upper)).T.copy()
        if self._P is not None:
            self._penalty_positions = entry_positions(pattern, rows[len(hu_rows):], cols[len(hu_cols):])
        self._cached_x = None
        self.modify_hessian = None           # a run's experimental Hessian hook (AngleNLP.solve)
        self.semidefinite_below_log_excess = -np.inf     # LogChordNLP's semidefinite_below_excess

    def _at(self, x, derivatives=True):
        """At x: z (4, t), the objective f, its gradient with respect to h (flat, triangle-major),
        the constraints g and, if derivatives, D (4 width, t).

        Cached for the last x, as IPOPT asks for all of them at the same point; D only once asked
        for (line-search trial points need only f and g).
        """
        if self._cached_x is None or not np.array_equal(x, self._cached_x):
            t = self.n_faces
            z = np.empty((4, t))
            z[:3] = x[:3 * t].reshape(t, 3).T
            z[3] = x[3 * t:]
            h = self._triangle(z, *self._parameters)[0].T.ravel()        # rows 8i.. of triangle i
            f = float(np.sum(h[::self._width]))
            seed = self._objective_rows
            if self._P is not None:
                residual = self._P @ h - 2 * np.pi
                f += self._penalty * float(residual @ residual)
                seed = seed + 2 * self._penalty * (self._P.T @ residual)
            self._cached = [z, f, seed, self._A @ h - self._b, None]
            self._cached_x = np.array(x, dtype=float)
        if derivatives and self._cached[4] is None:
            self._cached[4] = self._triangle_jacobian(self._cached[0], *self._parameters)[0]
        return self._cached

    def objective_and_constraints(self, x):
        _, f, _, g, _ = self._at(x, derivatives=False)
        return f, g

    def gradient(self, x):
        _, f, seed, _, d = self._at(x)
        t = self.n_faces
        # D^T seed triangle by triangle: each unknown belongs to one triangle
        per_unknown = np.einsum("crt,rt->ct", d.reshape(4, self._width, t), seed.reshape(t, self._width).T)
        return f, np.concatenate([per_unknown[:3].T.ravel(), per_unknown[3]])

    def jacobian(self, x):
        """(g, nonzeros of jac g in the order of ``jacobian_sparsity``)."""
        _, _, _, g, d = self._at(x)
        values = d.ravel()[self._jac_source]
        values[self._jac_negative] *= -1.0
        return g, values

    def hessian(self, x, lam_f, lam_g):
        """Nonzeros of the upper triangle of the Lagrangian's Hessian (``hessian_sparsity`` order)."""
        z, _, seed, _, d = self._at(x)
        weights = (lam_f * seed + self._At @ lam_g).reshape(self.n_faces, self._width).T
        blocks = self._triangle_hessian(z, *self._parameters, np.ascontiguousarray(weights))[0]
        tiny = np.flatnonzero(z[3] < self.semidefinite_below_log_excess)
        if len(tiny):
            blocks[:, tiny] = nearest_semidefinite_blocks(blocks[:, tiny])
        values = np.zeros(self._hessian_nnz)
        values[self._block_positions] = blocks
        if self._P is not None:
            pd = np.zeros(self._penalty_shape)
            np.add.at(pd, (self._penalty_rows, self._penalty_columns), d.ravel()[self._penalty_sources])
            outer = 2 * self._penalty * lam_f * (pd.T @ pd)
            np.add.at(values, self._penalty_positions, outer[self._penalty_upper])
        if self.modify_hessian is not None:
            values = self.modify_hessian(self, x, lam_f, lam_g, values)
        return values


class _NumpyFunction(ca.Callback):
    """A CasADi Function whose values come from a numpy function (of the inputs' nonzeros).

    ``inputs`` and ``outputs`` are lists of (name, Sparsity); ``evaluate`` takes one flat array per
    input and returns one array of nonzeros per output. Reads and writes CasADi's buffers directly.
    """

    def __init__(self, name, inputs, outputs, evaluate):
        ca.Callback.__init__(self)
        self._inputs, self._outputs, self._evaluate = inputs, outputs, evaluate
        self.construct(name, {})

    def get_n_in(self):
        return len(self._inputs)

    def get_n_out(self):
        return len(self._outputs)

    def get_name_in(self, i):
        return self._inputs[i][0]

    def get_name_out(self, i):
        return self._outputs[i][0]

    def get_sparsity_in(self, i):
        return self._inputs[i][1]

    def get_sparsity_out(self, i):
        return self._outputs[i][1]

    def has_eval_buffer(self):
        return True

    def eval_buffer(self, arg, res):
        # CasADi passes None for empty inputs and for outputs nobody asked for
        values = self._evaluate(*[np.empty(0) if a is None else np.frombuffer(a, dtype=float) for a in arg])
        for buffer, value in zip(res, values):
            if buffer is not None:
                np.frombuffer(buffer, dtype=float)[:] = value
        return 0


class _AngleProblem:
    """What the two kinds of angle NLP share: evaluation, bounds, IPOPT's set-up and its runs.

    A subclass builds ``_x`` (CasADi symbol), ``n_variables``, ``n_equalities``, ``n_inequalities``,
    ``_symbolic_problem()`` (and ``_numeric`` for numpy evaluation), and says its bounds on the
    variables (``_variable_lower_bounds``) and how they pack (``pack``, ``unpack``).
    """

    def _start(self, connectivity, formulation, n_variables):
        """The attributes every form sets first."""
        self.formulation = formulation
        self.connectivity = connectivity
        self.n_faces = connectivity.n_faces
        self.n_variables = n_variables
        self._numeric = None                 # _LogChordValues when IPOPT is to use numpy evaluation
        self._symbolic = None                # (objective, g_eq, g_ineq, derivatives) as CasADi graphs
        self._functions = None
        self._callbacks = None
        self._solvers = {}
        self.log_u_band = None               # (lower, upper) on log u where the bounds apply, or None
        # Seconds spent building this NLP (its numeric evaluators), booked as the first run's set-up.
        self.unbooked_build_s = 0.0

    def evaluate(self, x):
        """Objective and equality-constraint residuals at x (numpy)."""
        if self._numeric is not None:
            f, g = self._numeric.objective_and_constraints(np.asarray(x, float).ravel())
            return float(f), g.copy()                # the evaluator keeps g for its next callers
        if self._functions is None:
            objective, g_eq = self._symbolic_problem()[:2]
            self._functions = ca.Function("sphere_nlp_eval", [self._x], [objective, g_eq])
        f, g = self._functions(x)
        return float(f), np.asarray(g).ravel()

    def _numpy_problem(self):
        """nlpsol's problem and derivative Functions, evaluated by ``self._numeric`` (numpy); built once.

        CasADi keeps no reference to a Python Callback, so the NLP object holds them for all its
        solvers.
        """
        if self._callbacks is not None:
            return self._callbacks
        values = self._numeric
        n_x, n_g = self.n_variables, self.n_equalities
        x_in = ("x", ca.Sparsity.dense(n_x))
        p_in = ("p", ca.Sparsity(0, 1))
        scalar, g_out = ca.Sparsity.scalar(), ("g", ca.Sparsity.dense(n_g))
        functions = [
            _NumpyFunction("sphere_nlp_fg", [x_in], [("f", scalar), g_out],
                           values.objective_and_constraints),
            _NumpyFunction("nlp_grad_f", [x_in, p_in], [("f", scalar), ("grad_f_x", ca.Sparsity.dense(n_x))],
                           lambda x, p: values.gradient(x)),
            _NumpyFunction("nlp_jac_g", [x_in, p_in], [g_out, ("jac_g_x", values.jacobian_sparsity)],
                           lambda x, p: values.jacobian(x)),
            _NumpyFunction("nlp_hess_l", [x_in, p_in, ("lam_f", scalar), ("lam_g", ca.Sparsity.dense(n_g))],
                           [("triu_hess_gamma_x_x", values.hessian_sparsity)],
                           lambda x, p, lam_f, lam_g: [values.hessian(x, lam_f[0], lam_g)]),
        ]
        f, g = functions[0](self._x)
        self._callbacks = (f, g, dict(zip(("grad_f", "jac_g", "hess_lag"), functions[1:])), functions)
        return self._callbacks

    def _bounds(self, inequalities, excess_bounds=None, log_u_lower=None):
        lbx = self._variable_lower_bounds(inequalities, log_u_lower)
        ubx = np.full(self.n_variables, np.inf)
        if inequalities and self.log_u_band is not None:
            lower, upper = self.log_u_band
            t3 = 3 * self.n_faces
            lbx[:t3], ubx[:t3] = np.maximum(lbx[:t3], lower), upper
        if excess_bounds is not None:
            lbx[3 * self.n_faces:], ubx[3 * self.n_faces:] = excess_bounds
        lbg = np.zeros(self.n_equalities + (self.n_inequalities if inequalities else 0))
        ubg = np.zeros_like(lbg)
        if inequalities:
            ubg[self.n_equalities:] = np.inf
        return lbx, ubx, lbg, ubg

    def _solver(self, inequalities, options):
        key = (inequalities, tuple(sorted(options.items())))
        if key not in self._solvers:
            opts = {"print_time": False, "show_eval_warnings": False, "ipopt": dict(options)}
            # IPOPT prints its errors (MUMPS out of memory among them, OUT_OF_MEMORY_COMPLAINTS) from
            # print_level 1 only, and nothing else there: the captured output is scanned for them.
            if opts["ipopt"].get("print_level", 5) < 1:
                opts["ipopt"]["print_level"] = 1
            if self._numeric is not None:
                f, g, derivatives, _ = self._numpy_problem()
                # f, g and the multipliers come from IPOPT's last iterate: CasADi would otherwise
                # differentiate f and g once more after the solve (and there are no parameters)
                opts.update(derivatives, no_nlp_grad=True, calc_lam_p=False, calc_lam_x=False,
                            calc_f=False, calc_g=False)
            else:
                f, g_eq, g_ineq, derivatives = self._symbolic_problem()
                g = ca.vertcat(g_eq, g_ineq) if inequalities else g_eq
                if not inequalities or self.n_inequalities == 0:
                    opts.update(derivatives)       # exact derivatives built in linear time
            _, _, lbg, ubg = self._bounds(inequalities)
            callback = _ProgressCallback(self.n_variables, g.numel(), lbg, ubg)
            opts["iteration_callback"] = callback
            solver = ca.nlpsol("sphere_nlp", "ipopt", {"x": self._x, "f": f, "g": g}, opts)
            self._solvers[key] = (solver, callback)
        return self._solvers[key]

    def solve(self, x0, inequalities=False, lam_g0=None, lam_x0=None, options=None, progress=None,
              excess_bounds=None, log_u_lower=None, abort_violation=None, abort_iterations=50,
              sound_violation=0.0, on_iterate=None, modify_hessian=None):
        """Run IPOPT from x0.

        Parameters
        ----------
        x0 : (n_variables,) array
        inequalities : bool
            Add (3)-(5); otherwise only the equality constraints.
        lam_g0, lam_x0 : arrays, optional
            Multipliers to warm-start from (lam_g0 may cover the equalities only).
        options : dict
            IPOPT options (without the "ipopt." prefix).
        progress : callable(iteration, objective, violation, elapsed), optional
        excess_bounds : (lower, upper) arrays of length t, optional
            log-chord only: bounds on the log excesses (a trust region; see
            :func:`sphere_nlp.solve.solve_angles`).
        log_u_lower : (3t,) array, optional
            log-chord with ``inequalities=True`` only: lower bounds on log u per corner, instead of
            ``log(angle_margin)`` everywhere.
        abort_violation : float, optional
            Stop the run (status "Diverged") once the max constraint violation has stayed above
            this for ``abort_iterations`` iterations in a row: a run that has left the solution set
            that far rarely comes back and would otherwise spend its whole time limit.
        abort_iterations : int
        sound_violation : float
            With ``abort_violation``: the run keeps its iterate of least objective among those whose
            max violation is at most this (``IpoptRun.best_sound``), for a diverged run to resume from.
        on_iterate : callable(iteration, x, lam_g, lam_x, objective), optional
            Called with every iterate (copies), for traces and checkpoints.
        modify_hessian : callable(evaluator, x, lam_f, lam_g, values) -> values, optional
            log-chord with numpy evaluation only, for experiments: replaces the nonzeros ``values``
            of the Lagrangian Hessian's upper triangle handed to IPOPT at every evaluation.
            ``evaluator`` has ``hessian_sparsity`` and ``jacobian_sparsity`` (CasADi) and
            ``jacobian(x)`` -> (g, nonzeros); :func:`entry_positions` locates entries.

        Returns
        -------
        IpoptRun
        """
        lbx, ubx, lbg, ubg = self._bounds(inequalities, excess_bounds, log_u_lower)
        if interrupts.deadline_passed():
            # The run's time is up (interrupts.deadline): report the limit without building the
            # solver (seconds on a large mesh) or starting IPOPT.
            x0 = np.array(x0, dtype=float).ravel()
            return IpoptRun(x0=x0, x=x0.copy(), lam_g=np.zeros(len(lbg)), lam_x=np.zeros(len(x0)),
                            objective=float("nan"), status="Maximum_WallTime_Exceeded", iterations=0,
                            time_s=0.0, build_s=0.0, stats={})
        start = time.perf_counter()
        solver, callback = self._solver(inequalities, options or {})
        build_s = time.perf_counter() - start + self.unbooked_build_s
        self.unbooked_build_s = 0.0
        callback.reset(progress, abort_violation, abort_iterations, on_iterate, sound_violation)
        if modify_hessian is not None and self._numeric is None:
            raise ValueError("modify_hessian needs the log-chord form with numpy evaluation")
        args = dict(x0=x0, lbx=lbx, ubx=ubx, lbg=lbg, ubg=ubg)
        if lam_g0 is not None:
            lam = np.zeros(len(lbg))
            lam[:len(lam_g0)] = lam_g0
            args["lam_g0"] = lam
        if lam_x0 is not None:
            args["lam_x0"] = lam_x0
        start = time.perf_counter()
        if self._numeric is not None:
            self._numeric.modify_hessian = modify_hessian
        try:
            # A signal inside IPOPT is only recorded: raised inside a callback, CasADi would catch
            # it and IPOPT step around it; the iteration callback stops IPOPT instead
            # (interrupts.stop_requested), and the signal is raised once IPOPT has returned.
            with interrupts.defer_signals(), _c_stdout_captured() as c_output:
                callback.c_output = c_output
                out = solver(**args)
                callback.read_complaints()
        finally:
            callback.c_output = None
            if self._numeric is not None:
                self._numeric.modify_hessian = None
        interrupts.raise_if_interrupted()
        stats = solver.stats()
        status = stats.get("return_status", "unknown")
        if callback.linear_solver_failed:
            # The BLAS under MUMPS refused its arguments: every step from here is wrong.
            status = LINEAR_SOLVER_FAILED
        elif callback.aborted:
            status = "Diverged"
        elif status == "User_Requested_Stop" and interrupts.deadline_passed():
            status = "Maximum_WallTime_Exceeded"
        if callback.out_of_memory and status_kind(status) == "failed":
            # MUMPS could not get the memory to factorise, and IPOPT did not recover.
            status = LINEAR_SOLVER_OUT_OF_MEMORY
        return IpoptRun(x0=np.array(x0, dtype=float).ravel(), x=np.asarray(out["x"]).ravel(),
                        lam_g=np.asarray(out["lam_g"]).ravel(), lam_x=np.asarray(out["lam_x"]).ravel(),
                        objective=float(out["f"]), status=status, iterations=int(stats.get("iter_count", 0)),
                        time_s=time.perf_counter() - start, build_s=build_s, stats=stats, best_sound=callback.best)


class PaperNLP(_AngleProblem):
    """The paper's NLP as written (``faithful``) or with (6) substituted (``substituted``), one
    flat CasADi graph (see the module docstring).

    Parameters
    ----------
    connectivity : Connectivity
    targets : Targets
    formulation : {"substituted", "faithful"}
    dropped_vertices : sequence of int
        Vertices whose angle-sum constraint (7) is left out (see :class:`LogChordNLP`).

    Notes
    -----
    Variables are packed as ``x = [alpha.ravel(), e]`` (faithful) or ``x = alpha.ravel()``
    (substituted); use :meth:`pack` and :meth:`unpack`. Solver objects are created on first use,
    because CasADi derives the sparse Hessian then.
    """

    def __init__(self, connectivity, targets, formulation="substituted", dropped_vertices=()):
        if formulation not in ("substituted", "faithful"):
            raise ValueError("PaperNLP's formulation is 'substituted' or 'faithful', not %r" % (formulation,))
        t = connectivity.n_faces
        self._start(connectivity, formulation, 3 * t + (0 if formulation == "substituted" else t))
        kept_vertices = np.setdiff1d(np.arange(connectivity.n_vertices), dropped_vertices)
        x, objective, g_eq, g_ineq = self._build_paper_form(connectivity, targets, formulation, kept_vertices)
        self._x, self._symbolic = x, (objective, g_eq, g_ineq, {})
        self.n_equalities, self.n_inequalities = g_eq.numel(), g_ineq.numel()

    def _symbolic_problem(self):
        """(objective, g_eq, g_ineq, derivatives): the problem as CasADi graphs of ``self._x``."""
        return self._symbolic

    def _variable_lower_bounds(self, inequalities, log_u_lower=None):
        lbx = np.full(self.n_variables, -np.inf)
        if inequalities:
            lbx[:] = 0.0          # (3) alpha > 0 and, for the faithful form, (4) e > 0
        return lbx

    @staticmethod
    def _build_paper_form(connectivity, targets, formulation, kept_vertices):
        """The paper's constraints on alpha (and e), as one flat SX graph."""
        t = connectivity.n_faces
        corner = np.arange(3 * t)
        base, local = 3 * (corner // 3), corner % 3
        prev_idx = (base + (local + 2) % 3).tolist()
        next_idx = (base + (local + 1) % 3).tolist()
        edge_corners = connectivity.edge_corner_indices()
        n_alpha = 3 * t
        n_x = n_alpha + (0 if formulation == "substituted" else t)
        x = ca.SX.sym("x", n_x)
        excess_index = np.repeat(np.arange(t), 3).tolist()
        alpha = x[:n_alpha]
        triangle_sums = ca.sum1(ca.reshape(alpha, 3, t)).T              # alpha0 + alpha1 + alpha2
        if formulation == "faithful":
            e = x[n_alpha:]
            triangle_condition = triangle_sums - e - np.pi
        else:
            e = triangle_sums - np.pi                                 # (6) solved for e
            triangle_condition = None
        cosines = edge_cosines_sx(alpha, prev_idx, next_idx)
        edge_condition = cosines[edge_corners[:, 0].tolist()] - cosines[edge_corners[:, 1].tolist()]
        vertex_matrix = connectivity.vertex_corner_matrix()[kept_vertices]
        vertex_sums = ca.mtimes(_sparse_dm(vertex_matrix), alpha) - 2 * np.pi

        equalities = [vertex_sums, edge_condition]
        if triangle_condition is not None:
            equalities.insert(0, triangle_condition)
        g_eq = ca.vertcat(*equalities)

        inequalities = [2 * alpha - e[excess_index]]                  # (5): e < 2 alpha
        if formulation == "substituted":
            inequalities.insert(0, e)                                 # (4): e > 0
        g_ineq = ca.vertcat(*inequalities)

        beta = targets.angles.ravel()
        objective = (targets.angle_weight * ca.dot(targets.corner_weights.ravel(), (alpha - beta) ** 2)
                     + targets.area_weight * ca.sumsqr((e - targets.excess) / targets.excess_scale))

        return x, objective, g_eq, g_ineq

    def pack(self, angles, excess=None):
        """Variables vector from angles (t, 3) (and excess (t,) for the faithful form)."""
        angles = np.asarray(angles, float).ravel()
        if self.formulation == "faithful":
            if excess is None:
                excess = angles.reshape(-1, 3).sum(1) - np.pi
            return np.concatenate([angles, np.asarray(excess, float)])
        return angles

    def unpack(self, x):
        """(angles (t, 3), excess (t,)) from a variables vector."""
        x = np.asarray(x, float).ravel()
        angles = x[:3 * self.n_faces].reshape(-1, 3)
        if self.formulation == "faithful":
            return angles, x[3 * self.n_faces:].copy()
        return angles, angles.sum(1) - np.pi


class LogChordNLP(_AngleProblem):
    """The log-chord NLP (the default formulation; see the module docstring): unknowns log u and log e,
    evaluated by numpy over all triangles at once with exact structured derivatives.

    Parameters
    ----------
    connectivity : Connectivity
    targets : Targets
    dropped_vertices : sequence of int
        Vertices whose angle-sum constraint (7) is left out. At a solution the equality Jacobian has
        exactly three redundant rows (its left null space is spanned by the vertex coordinates
        x, y, z), which makes the KKT matrix singular; leaving out (7) at three vertices whose
        positions are linearly independent removes the redundancy, and those three sums then hold
        automatically. :func:`sphere_nlp.solve.solve_angles` checks all of (7) afterwards.
    angle_margin : float
        With ``inequalities=True`` every u = alpha - e/2 is kept >= this (radians).
    dropped_penalty : float
        Weight of the penalty on the left-out vertex sums.
    area_form : {"linear", "log"}
        The area term of the objective. ``"linear"`` is (9),
        ``area_weight * sum(((e - e') / e_mean)^2)``; ``"log"`` is
        ``area_weight * sum(w (log e - log e')^2)``, convex in the unknown log e, which the area modes
        solve first (:func:`sphere_nlp.solve.area_continuation`) before (9) itself.
    log_area_weights : (t,) array, optional
        The weights w of the "log" area term (default 1 for every triangle).
    log_u_band : pair of (3t,) arrays, optional
        Lower and upper bounds on log u (-inf, inf where none) that the runs with bounds add to
        their own (:func:`sphere_nlp.solve.sliver_band_bounds`).
    obtuse_corners : (t, 3) bool array, optional
        Corners whose sin alpha and sin u in (8) are written through the other two
        corners (sin alpha_j = sin(u_k + u_l), sin u_j = sin(u_k + u_l + e/2), equal under (6)),
        which stays well-conditioned near alpha = pi; :func:`sphere_nlp.solve.solve_angles` flags
        the corners above pi/2 where a stage starts. Same feasible set and optima either way.
    hessian : {"exact", "clipped", "clipped-corners"}
        The Hessian handed to IPOPT. ``"exact"`` (default) is the Lagrangian's.
        ``"clipped"`` leaves out the negative part of the term that the logarithmic unknowns add:
        with x = exp(z) (x = u or e), the Hessian in z is D H_x D + diag(dL/dz), D = diag(x), and
        ``"clipped"`` adds only max(dL/dz, 0) on the diagonal. dL/dz vanishes at a KKT point
        wherever no bound is active (and equals the bound's multiplier, >= 0, where a lower bound
        is), so the optima and IPOPT's fast local convergence are unchanged; away from them that
        term made the Hessian indefinite on every iteration of the area modes' long middle, and
        IPOPT's inertia correction added 1e-2..1e-1 times the identity instead, a step more like
        gradient descent (see :class:`sphere_nlp.settings.SolverSettings`' ``area_mode_hessian``).
        ``"clipped-corners"`` clips only the corners' log u and keeps the log e entries exact: their
        negative part is what keeps the first steps short while a start is far from the optimum
        (the angle modes' ``angle_mode_hessian``).
    evaluation : {"numpy", "casadi"}
        How IPOPT's function and derivative values are computed: by numpy over all
        triangles at once (default, faster), or by CasADi's interpreter one triangle at a time
        (the reference). The same numbers up to rounding.
    semidefinite_below_excess : float
        Numpy evaluation only: the Hessian block of every triangle whose excess is below this
        (radians) is handed to IPOPT with its negative eigenvalues set to 0
        (:func:`nearest_semidefinite_blocks`; 0, the default, never). On a thin limb's tips, far below
        what positions hold, those blocks make the Lagrangian's Hessian indefinite on most
        iterations, and IPOPT's inertia correction then adds a multiple of the identity to all of
        it, which stalls the steps along the limb. Only the path changes: the KKT points are the
        same (docs/tuning.md, "semidefinite_block_share").

    Notes
    -----
    Variables are packed as ``x = [log u.ravel(), log e]``, u = alpha - e/2; use :meth:`pack` and
    :meth:`unpack`. Solver objects are created on first use.
    """

    def __init__(self, connectivity, targets, dropped_vertices=(), angle_margin=DEFAULT_SETTINGS.angle_margin,
                 dropped_penalty=DEFAULT_SETTINGS.dropped_penalty, area_form="linear", obtuse_corners=None,
                 evaluation="numpy", hessian="exact", log_area_weights=None, log_u_band=None,
                 semidefinite_below_excess=0.0):
        if evaluation not in EVALUATIONS:
            raise ValueError("evaluation must be one of %s, not %r" % (EVALUATIONS, evaluation))
        if area_form not in ("linear", "log"):
            raise ValueError("area_form must be 'linear' or 'log', not %r" % (area_form,))
        if hessian not in HESSIANS:
            raise ValueError("hessian must be one of %s, not %r" % (HESSIANS, hessian))
        began = time.perf_counter()
        t = connectivity.n_faces
        self._start(connectivity, "log-chord", 4 * t)
        self.angle_margin = float(angle_margin)
        self.log_u_band = log_u_band
        if obtuse_corners is None:
            obtuse_corners = np.zeros((t, 3), dtype=bool)
        obtuse_corners = np.asarray(obtuse_corners, dtype=bool)
        if obtuse_corners.shape != (t, 3):
            raise ValueError("obtuse_corners must be a (t, 3) boolean array")
        if log_area_weights is None:
            log_area_weights = np.ones(t)
        log_area_weights = np.asarray(log_area_weights, dtype=float)
        if log_area_weights.shape != (t,) or not (log_area_weights >= 0).all():
            raise ValueError("log_area_weights must be a non-negative (t,) array")
        kept_vertices = np.setdiff1d(np.arange(connectivity.n_vertices), dropped_vertices)
        self._parts = self._log_chord_parts(connectivity, targets, kept_vertices, dropped_penalty,
                                            area_form, obtuse_corners=obtuse_corners, hessian=hessian,
                                            log_area_weights=log_area_weights)
        self._x = ca.MX.sym("x", self.n_variables)
        self.n_equalities = self._parts["A"].shape[0]
        self.n_inequalities = 0          # (3)-(5) hold by construction (see the module docstring)
        if evaluation == "numpy":
            self._numeric = _LogChordValues(self._parts)
            if semidefinite_below_excess > 0:
                self._numeric.semidefinite_below_log_excess = float(np.log(semidefinite_below_excess))
        elif semidefinite_below_excess > 0:
            raise ValueError("semidefinite_below_excess needs the numpy evaluation")
        self.unbooked_build_s = time.perf_counter() - began

    def _variable_lower_bounds(self, inequalities, log_u_lower=None):
        lbx = np.full(self.n_variables, -np.inf)
        if inequalities:
            # u > 0 holds anyway; the bound keeps every u = alpha - e/2 at least a margin from 0,
            # because on some meshes the infimum of the objective is at a degenerate triangle.
            lbx[:3 * self.n_faces] = np.log(self.angle_margin) if log_u_lower is None else log_u_lower
        return lbx

    def _symbolic_problem(self):
        """(objective, g_eq, g_ineq, derivatives): the problem as CasADi graphs of ``self._x``.

        Built on first use for the log-chord form (the numpy evaluation does not need it; it took
        half of the NLP's build time at 100k triangles).
        """
        if self._symbolic is None:
            objective, g_eq, derivatives = self._log_chord_graph(self._x, self._parts)
            self._symbolic = (objective, g_eq, ca.MX(0, 1), derivatives)
        return self._symbolic

    @staticmethod
    def _log_chord_parts(connectivity, targets, kept_vertices, dropped_penalty=0.0, area_form="linear", *,
                         obtuse_corners, log_area_weights, hessian="exact"):
        """The log-chord form as g = A h(z) - b, with h one small function of each triangle's unknowns.

        Every term of the objective and of (6)-(8) depends on one triangle's unknowns
        z = (log u0, log u1, log u2, log e): per triangle, h = [objective term, (6), alpha0..2,
        log half-chords 0..2]. The exact derivatives follow from that structure without asking
        CasADi to differentiate the whole graph (which costs superlinear time in sparsity
        detection: 10 s at 10k vertices): with D = dh/dx (dense 8x4 blocks, one per triangle),

            jac g = A D,   grad f = D^T c,   Hessian of the Lagrangian = sum over triangles of
            the 4x4 Hessian of w_i . h_i,  w = sigma c + A^T lambda,

        where c picks the objective rows (plus the dropped-vertex penalty's terms). The 4-variable
        derivatives are derived once (SX); :class:`_LogChordValues` evaluates them over all
        triangles in numpy, :meth:`_log_chord_graph` maps them over the triangles in CasADi.
        About 70 lines on purpose: the per-triangle functions and the index arrays of A, P and D
        share one row layout (8 rows of h per triangle), kept in one place.

        Returns
        -------
        dict with the per-triangle SX Functions ``triangle``, ``triangle_jacobian``,
        ``triangle_hessian`` (its ``upper`` entries), ``variable_of`` (t, 4) (each triangle's
        unknowns), ``A`` (scipy CSR), ``b``, ``parameters`` (beta (3, t), e' (1, t), obtuse flags
        (3, t), corner weights (3, t), weights of the "log" area term (1, t)), ``objective_rows``,
        ``P`` (scipy CSR: the left-out vertex sums, or None), ``dropped_penalty``.
        """
        t, n = connectivity.n_faces, connectivity.n_vertices
        width = 8                                        # rows of h per triangle
        z = ca.SX.sym("z", 4)
        beta = ca.SX.sym("beta", 3)
        excess_target = ca.SX.sym("excess_target")
        weights = ca.SX.sym("w", width)
        obtuse = ca.SX.sym("obtuse", 3)                  # 1 at a corner flagged obtuse, else 0
        corner_weight = ca.SX.sym("corner_weight", 3)
        log_area_weight = ca.SX.sym("log_area_weight")
        u, e = ca.exp(z[:3]), ca.exp(z[3])
        alpha = u + e / 2
        # Half-angle cosine rule: sin^2(a_j/2) = sin(e/2) sin(alpha_j - e/2) / (sin alpha_k sin alpha_l).
        # Near alpha = pi, sin alpha and sin u are differences from pi of large unknowns, and their
        # logs swing wildly under small steps in log u (nefertiti.obj original-angles: the worst
        # constraints were always the three edges of a 177-179.3 deg sliver, violated by up to 1.1).
        # At corners flagged obtuse they are written instead as sines of the other corners' small
        # sums, equal to them under (6): sin alpha_j = sin(u_k + u_l), sin u_j = sin(u_k + u_l + e/2).
        # (Doing that at every corner gave bunny equal-angles 36 iterations instead of 23.)
        others = [u[(j + 1) % 3] + u[(j + 2) % 3] for j in range(3)]
        sin_alpha = [(1 - obtuse[j]) * ca.sin(alpha[j]) + obtuse[j] * ca.sin(others[j]) for j in range(3)]
        sin_u = [(1 - obtuse[j]) * ca.sin(u[j]) + obtuse[j] * ca.sin(others[j] + e / 2) for j in range(3)]
        log_half_chords = [ca.log(ca.sin(e / 2)) + ca.log(sin_u[j]) - ca.log(sin_alpha[(j + 1) % 3])
                           - ca.log(sin_alpha[(j + 2) % 3]) for j in range(3)]
        if area_form == "log":
            area_term = log_area_weight * (z[3] - ca.log(excess_target)) ** 2
        else:
            area_term = ((e - excess_target) / targets.excess_scale) ** 2
        # Corner weights (Targets.corner_weights): ones for the paper's (9), 1/beta^2 scaled for
        # relative errors as in angle-based flattening.
        term = (targets.angle_weight * ca.dot(corner_weight, (alpha - beta) ** 2)
                + targets.area_weight * area_term)
        h_sx = ca.vertcat(term, ca.sum1(u) + e / 2 - np.pi, alpha, *log_half_chords)
        inputs = [z, beta, excess_target, obtuse, corner_weight, log_area_weight]
        triangle = ca.Function("sphere_nlp_triangle", inputs, [h_sx])
        jacobian_8x4 = ca.jacobian(h_sx, z)
        triangle_jacobian = ca.Function("sphere_nlp_triangle_jac", inputs,
                                        [ca.vec(ca.densify(jacobian_8x4))])
        hessian_4x4 = ca.densify(ca.hessian(ca.dot(weights, h_sx), z)[0])
        if hessian != "exact":
            # Each unknown z_c belongs to this triangle only, so this is dL/dz of the whole problem.
            lagrangian_gradient = ca.mtimes(jacobian_8x4.T, weights)
            clipped = np.array([1.0, 1.0, 1.0, 1.0 if hessian == "clipped" else 0.0])
            hessian_4x4 = hessian_4x4 - ca.diag(ca.fmin(lagrangian_gradient, 0) * clipped)
        upper = BLOCK_UPPER_ENTRIES
        triangle_hessian = ca.Function("sphere_nlp_triangle_hess", inputs + [weights],
                                       [ca.vertcat(*[hessian_4x4[i, j] for i, j in upper])])

        # A picks and combines entries of h (rows 8i..8i+7 hold triangle i's values).
        corner = np.arange(3 * t)
        alpha_row = 2 + corner % 3 + width * (corner // 3)
        row_of_vertex = np.full(n, -1)
        row_of_vertex[kept_vertices] = np.arange(len(kept_vertices))
        at_kept = row_of_vertex[connectivity.faces.ravel()] >= 0
        edge_corners = connectivity.edge_corner_indices()
        m = len(edge_corners)
        n_kept = len(kept_vertices)
        rows = np.concatenate([np.arange(t),                                             # (6)
                               t + row_of_vertex[connectivity.faces.ravel()][at_kept],   # (7)
                               t + n_kept + np.arange(m), t + n_kept + np.arange(m)])     # (8)
        cols = np.concatenate([1 + width * np.arange(t), alpha_row[at_kept],
                               5 + edge_corners[:, 0] % 3 + width * (edge_corners[:, 0] // 3),
                               5 + edge_corners[:, 1] % 3 + width * (edge_corners[:, 1] // 3)])
        values = np.concatenate([np.ones(t + at_kept.sum() + m), -np.ones(m)])
        A = sp.csr_matrix((values, (rows, cols)), shape=(t + n_kept + m, width * t))
        b = np.concatenate([np.zeros(t), np.full(n_kept, 2 * np.pi), np.zeros(m)])
        objective_rows = np.zeros(width * t)
        objective_rows[::width] = 1.0

        dropped = np.setdiff1d(np.arange(n), kept_vertices)
        P = None
        if len(dropped) and dropped_penalty > 0:
            # The left-out vertex sums as a penalty: zero with zero gradient at every solution of the
            # full problem, so its optima stay stationary, but it stops the solver settling on a
            # metric with cone points at the left-out vertices (bunny.off: sums off by 0.24 without).
            row_of_dropped = np.full(n, -1)
            row_of_dropped[dropped] = np.arange(len(dropped))
            at_dropped = row_of_dropped[connectivity.faces.ravel()] >= 0
            P = sp.csr_matrix((np.ones(at_dropped.sum()),
                               (row_of_dropped[connectivity.faces.ravel()][at_dropped],
                                alpha_row[at_dropped])), shape=(len(dropped), width * t))
        # D = dh/dx: triangle i's 8x4 block sits in rows 8i.., columns of its z (3i+c, or 3t+i for e),
        # its entries in the order the per-triangle Jacobian returns them: triangle, then column c,
        # then row r (vec of 8x4 is column-major).
        tri = np.arange(t)
        variable_of = np.stack([3 * tri, 3 * tri + 1, 3 * tri + 2, 3 * t + tri], axis=1)     # (t, 4)
        r_idx, c_idx = np.meshgrid(np.arange(width), np.arange(4), indexing="ij")
        d_rows = (width * tri[:, None] + r_idx.T.ravel()[None, :]).ravel()
        d_cols = variable_of[:, c_idx.T.ravel()].ravel()
        return dict(triangle=triangle, triangle_jacobian=triangle_jacobian, triangle_hessian=triangle_hessian,
                    upper=upper, variable_of=variable_of, d_rows=d_rows, d_cols=d_cols,
                    A=A, b=b, objective_rows=objective_rows, P=P, dropped_penalty=dropped_penalty,
                    parameters=(targets.angles.T, targets.excess.reshape(1, -1),
                                np.asarray(obtuse_corners, dtype=float).T, targets.corner_weights.T,
                                log_area_weights.reshape(1, -1)))

    @staticmethod
    def _log_chord_graph(x, parts):
        """The log-chord problem as a CasADi MX graph of x, with its exact derivatives.

        The per-triangle functions of :meth:`_log_chord_parts`, mapped over the triangles; the
        reference that the numpy evaluation (:class:`_LogChordValues`) is tested against.

        Returns
        -------
        objective, g_eq : MX
        derivatives : dict of CasADi Functions for nlpsol (grad_f, jac_g, hess_lag)
        """
        variable_of, upper = parts["variable_of"], parts["upper"]
        t = len(variable_of)
        width = parts["A"].shape[1] // t
        A, P, penalty = _sparse_dm(parts["A"]), parts["P"], parts["dropped_penalty"]
        Z = ca.vertcat(ca.reshape(x[:3 * t], 3, t), ca.reshape(x[3 * t:], 1, t))
        parameters = [ca.DM(p) for p in parts["parameters"]]
        h = ca.reshape(parts["triangle"].map(t)(Z, *parameters), width * t, 1)
        g_eq = ca.mtimes(A, h) - parts["b"]
        objective = ca.sum1(h[::width])
        seed = ca.DM(parts["objective_rows"])
        if P is not None:
            P = _sparse_dm(P)
            objective = objective + penalty * ca.sumsqr(ca.mtimes(P, h) - 2 * np.pi)
            seed = seed + 2 * penalty * ca.mtimes(P.T, ca.mtimes(P, h) - 2 * np.pi)

        D = _mx_from_triplets(parts["d_rows"], parts["d_cols"],
                              ca.vec(parts["triangle_jacobian"].map(t)(Z, *parameters)), width * t, 4 * t)
        h_sym = [x, ca.MX.sym("p", 0, 1)]
        lam_f = ca.MX.sym("lam_f")
        lam_g = ca.MX.sym("lam_g", g_eq.numel())
        grad_f = ca.Function("nlp_grad_f", h_sym, [objective, ca.mtimes(D.T, seed)],
                             ["x", "p"], ["f", "grad_f_x"])
        jac_g = ca.Function("nlp_jac_g", h_sym, [g_eq, ca.mtimes(A, D)], ["x", "p"], ["g", "jac_g_x"])
        W = ca.reshape(lam_f * seed + ca.mtimes(A.T, lam_g), width, t)
        hu_rows = np.array([i for i, _ in upper])
        hu_cols = np.array([j for _, j in upper])
        H = _mx_from_triplets(variable_of[:, hu_rows].ravel(), variable_of[:, hu_cols].ravel(),
                              ca.vec(parts["triangle_hessian"].map(t)(Z, *parameters, W)), 4 * t, 4 * t)
        if P is not None:
            PD = ca.mtimes(P, D)
            H = H + ca.triu(2 * penalty * lam_f * ca.mtimes(PD.T, PD))
        hess_lag = ca.Function("nlp_hess_l", h_sym + [lam_f, lam_g], [H],
                               ["x", "p", "lam_f", "lam_g"], ["triu_hess_gamma_x_x"])
        return objective, g_eq, {"grad_f": grad_f, "jac_g": jac_g, "hess_lag": hess_lag}

    def pack(self, angles, excess=None):
        """Variables (log u, log e) from angles (t, 3) and excess (t,) (default: from (6))."""
        angles = np.asarray(angles, float)
        if excess is None:
            excess = angles.sum(1) - np.pi
        u = angles - np.asarray(excess)[:, None] / 2
        # A start outside the valid region is moved just inside it (the logarithm needs u, e > 0).
        u = np.where(u > 0, u, 1e-3).ravel()
        excess = np.where(excess > 0, excess, 1e-3 * 4 * np.pi / len(excess))
        return np.log(np.concatenate([u, excess]))

    def unpack(self, x):
        """(angles (t, 3), excess (t,)) from a variables vector."""
        x = np.asarray(x, float).ravel()
        angles = x[:3 * self.n_faces].reshape(-1, 3)
        excess = np.exp(x[3 * self.n_faces:])
        return np.exp(angles) + excess[:, None] / 2, excess


def AngleNLP(connectivity, targets, formulation=DEFAULT_FORMULATION, dropped_vertices=(), **log_chord_options):
    """The angle NLP of one mesh and one set of targets in the given formulation.

    ``"log-chord"``: a :class:`LogChordNLP` (``log_chord_options`` are its keywords: angle_margin,
    dropped_penalty, area_form, obtuse_corners, evaluation, hessian); ``"substituted"`` and
    ``"faithful"``: a :class:`PaperNLP`. Both have ``pack``, ``unpack``, ``evaluate`` and ``solve``
    (IPOPT from a point, returning an :class:`IpoptRun`).

    ``dropped_vertices`` are the vertices whose angle-sum constraint (7) is left out (see
    :class:`LogChordNLP`).
    """
    if formulation not in FORMULATIONS:
        raise ValueError("unknown formulation %r; choose one of %s" % (formulation, FORMULATIONS))
    if formulation == "log-chord":
        return LogChordNLP(connectivity, targets, dropped_vertices, **log_chord_options)
    if log_chord_options:
        raise TypeError("%s are options of the log-chord formulation only" % ", ".join(sorted(log_chord_options)))
    return PaperNLP(connectivity, targets, formulation, dropped_vertices)
