"""The angle NLP (sphere_nlp.nlp): derivatives against CasADi and finite differences, the numpy
evaluation, the obtuse form of (8), the divergence watch."""

import numpy as np
import pytest

from sphere_nlp.certify import signed_solid_angles, spherical_angles
from sphere_nlp.connectivity import build_connectivity
from sphere_nlp.nlp import AngleNLP
from sphere_nlp.settings import SolverSettings
from sphere_nlp.solve import independent_vertices
from sphere_nlp.targets import make_targets

from conftest import small_log_chord_problem
from meshgen import ellipsoid

SETTINGS = SolverSettings()


@pytest.mark.parametrize("formulation", ["substituted", "faithful", "log-chord"])
def test_jacobian_matches_finite_differences(formulation):
    import casadi as ca

    V, F = ellipsoid(1)
    c = build_connectivity(F, len(V))
    nlp = AngleNLP(c, make_targets("original-angles", V, F, c.vertex_degree), formulation)
    rng = np.random.default_rng(1)
    angles = np.full((c.n_faces, 3), np.pi / 3) + 0.05 * rng.random((c.n_faces, 3))
    x = nlp.pack(angles, angles.sum(1) - np.pi + 0.01)
    g_eq = nlp._symbolic_problem()[1]
    jac = ca.Function("j", [nlp._x], [ca.jacobian(g_eq, nlp._x)])(x).full()
    step = 1e-6
    for k in rng.choice(len(x), 12, replace=False):
        dx = np.zeros_like(x)
        dx[k] = step
        fd = (nlp.evaluate(x + dx)[1] - nlp.evaluate(x - dx)[1]) / (2 * step)
        np.testing.assert_allclose(jac[:, k], fd, atol=1e-7)


@pytest.mark.parametrize("dropped, with_obtuse, weighting", [([], False, "uniform"), ([0, 5, 11], False, "relative"),
                                                             ([0, 5, 11], True, "uniform"),
                                                             ([0, 5, 11], True, "relative")])
def test_structured_derivatives_match_casadi_ad(dropped, with_obtuse, weighting):
    # The log-chord form hands IPOPT exact derivatives assembled from its per-triangle structure,
    # either as CasADi graphs (evaluation="casadi") or in numpy (the default); both must equal
    # CasADi's automatic differentiation of the same objective and constraints.
    import casadi as ca

    V, F = ellipsoid(1)
    c = build_connectivity(F, len(V))
    rng = np.random.default_rng(2)
    obtuse = rng.random((c.n_faces, 3)) < 0.3 if with_obtuse else None
    # Relative weighting: per-corner weights that differ (1 / beta^2 of the 3D angles).
    targets = make_targets("original-areas", V, F, c.vertex_degree, angle_weight=1.0, corner_weighting=weighting)
    nlp = AngleNLP(c, targets, "log-chord", dropped_vertices=dropped, obtuse_corners=obtuse)
    angles = np.full((c.n_faces, 3), np.pi / 3) + 0.1 * rng.random((c.n_faces, 3))
    x = nlp.pack(angles, angles.sum(1) - np.pi + 0.02)
    lam_f, lam_g = 0.7, rng.standard_normal(nlp.n_equalities)
    X = nlp._x
    f, g, _, graph_derivatives = nlp._symbolic_problem()
    reference = ca.Function("ad", [X], [f, g, ca.gradient(f, X), ca.jacobian(g, X),
                                        ca.hessian(lam_f * f + ca.dot(ca.DM(lam_g), g), X)[0]])
    f_ad, g_ad, grad_ad, jac_ad, hess_ad = (m.full() for m in reference(x))
    numpy_f, numpy_g, numpy_derivatives, _ = nlp._numpy_problem()
    np.testing.assert_allclose(ca.Function("fg", [X], [numpy_f, numpy_g])(x)[1].full(), g_ad, atol=1e-12)
    assert abs(nlp.evaluate(x)[0] - f_ad.item()) <= 1e-12 * abs(f_ad.item())
    for d in (graph_derivatives, numpy_derivatives):
        grad = d["grad_f"](x, ca.DM.zeros(0, 1))[1].full().ravel()
        jac = d["jac_g"](x, ca.DM.zeros(0, 1))[1].full()
        hess_upper = d["hess_lag"](x, ca.DM.zeros(0, 1), lam_f, lam_g).full()
        np.testing.assert_allclose(grad, grad_ad.ravel(), rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(jac, jac_ad, rtol=1e-10, atol=1e-10)
        assert np.allclose(np.tril(hess_upper, -1), 0)
        np.testing.assert_allclose(np.triu(hess_upper), np.triu(hess_ad), rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("hessian", ["clipped", "clipped-corners"])
def test_clipped_hessian_is_the_exact_one_less_the_negative_log_term(hessian):
    # hessian="clipped" drops min(dL/dz, 0) from the diagonal of the Lagrangian's Hessian in the
    # log unknowns z (the part the change of variables adds, which vanishes at KKT points);
    # "clipped-corners" only in the corners' log u, keeping the log e entries exact. Checked
    # against CasADi's automatic differentiation, for both evaluations.
    import casadi as ca

    V, F = ellipsoid(1)
    c = build_connectivity(F, len(V))
    rng = np.random.default_rng(3)
    targets = make_targets("equal-areas", V, F, c.vertex_degree)
    angles = np.full((c.n_faces, 3), np.pi / 3) + 0.1 * rng.random((c.n_faces, 3))
    lam_f = 0.7
    for evaluation in ("numpy", "casadi"):
        nlp = AngleNLP(c, targets, "log-chord", dropped_vertices=[0, 5, 11], hessian=hessian,
                       evaluation=evaluation)
        x = nlp.pack(angles, angles.sum(1) - np.pi + 0.02)
        lam_g = rng.standard_normal(nlp.n_equalities)
        X = nlp._x
        f, g = nlp._symbolic_problem()[:2]
        lagrangian = lam_f * f + ca.dot(ca.DM(lam_g), g)
        gradient, exact = (m.full() for m in ca.Function("ad", [X], [ca.gradient(lagrangian, X),
                                                                    ca.hessian(lagrangian, X)[0]])(x))
        clipped_unknowns = np.arange(nlp.n_variables) < (4 if hessian == "clipped" else 3) * c.n_faces
        expected = exact - np.diag(np.where(clipped_unknowns, np.minimum(gradient.ravel(), 0.0), 0.0))
        assert (gradient[clipped_unknowns] < -1e-3).sum() > 10      # the clipping does something here
        if hessian == "clipped-corners":
            assert (gradient[~clipped_unknowns] < -1e-3).sum() > 10      # and leaves some out
        derivatives = nlp._numpy_problem()[2] if evaluation == "numpy" else nlp._symbolic_problem()[3]
        clipped = derivatives["hess_lag"](x, ca.DM.zeros(0, 1), lam_f, lam_g).full()
        np.testing.assert_allclose(np.triu(clipped), np.triu(expected), rtol=1e-9, atol=1e-9)


def test_semidefinite_blocks_are_the_nearest_positive_semidefinite_matrices():
    # Higham (1988): the nearest PSD matrix in the Frobenius norm sets the negative eigenvalues to
    # 0, so its distance is the norm of those eigenvalues; PSD blocks are left as they are.
    from sphere_nlp.nlp import BLOCK_UPPER_ENTRIES, nearest_semidefinite_blocks

    rng = np.random.default_rng(4)
    rows, cols = np.array(BLOCK_UPPER_ENTRIES).T
    matrices = rng.standard_normal((50, 4, 4))
    matrices = matrices + matrices.transpose(0, 2, 1)
    projected = nearest_semidefinite_blocks(matrices[:, rows, cols].T)
    full = np.zeros_like(matrices)
    full[:, rows, cols] = projected.T
    full[:, cols, rows] = projected.T
    eigenvalues = np.linalg.eigvalsh(matrices)
    assert (eigenvalues < 0).any(axis=1).sum() > 40                     # most need projecting
    assert np.linalg.eigvalsh(full).min() >= -1e-12
    distance = np.linalg.norm(full - matrices, axis=(1, 2))
    np.testing.assert_allclose(distance, np.linalg.norm(np.minimum(eigenvalues, 0), axis=1), atol=1e-12)
    np.testing.assert_allclose(nearest_semidefinite_blocks(projected), projected, atol=1e-12)


def test_semidefinite_below_excess_projects_only_the_tiny_triangles_blocks():
    # LogChordNLP(semidefinite_below_excess=s): the Hessian handed to IPOPT is the exact one except
    # on the 4x4 blocks of triangles whose excess is below s, which are made positive semidefinite.
    import casadi as ca

    V, F = ellipsoid(1)
    c = build_connectivity(F, len(V))
    rng = np.random.default_rng(5)
    targets = make_targets("original-angles", V, F, c.vertex_degree)
    angles = np.full((c.n_faces, 3), np.pi / 3) + 0.1 * rng.random((c.n_faces, 3))
    excess = angles.sum(1) - np.pi + 0.02
    tiny = np.arange(c.n_faces) % 3 == 0
    excess[tiny] = 1e-20
    lam_f = 0.7
    hessians = {}
    for below in (0.0, 1e-18):
        nlp = AngleNLP(c, targets, "log-chord", dropped_vertices=[0, 5, 11], semidefinite_below_excess=below)
        x = nlp.pack(angles, excess)
        lam_g = np.random.default_rng(6).standard_normal(nlp.n_equalities)
        upper = nlp._numpy_problem()[2]["hess_lag"](x, ca.DM.zeros(0, 1), lam_f, lam_g).full()
        hessians[below] = np.triu(upper) + np.triu(upper, 1).T
    t = c.n_faces
    variables = np.stack([3 * np.arange(t), 3 * np.arange(t) + 1, 3 * np.arange(t) + 2, 3 * t + np.arange(t)], 1)
    negative = 0
    for i in range(t):
        block = np.ix_(variables[i], variables[i])
        exact, handed = hessians[0.0][block], hessians[1e-18][block]
        if tiny[i]:
            assert np.linalg.eigvalsh(handed).min() >= -1e-9 * max(1.0, np.abs(exact).max())
            negative += np.linalg.eigvalsh(exact).min() < -1e-6
        else:
            np.testing.assert_array_equal(handed, exact)
    assert negative > 10                                           # the projection did something
    with pytest.raises(ValueError, match="numpy evaluation"):
        AngleNLP(c, targets, "log-chord", evaluation="casadi", semidefinite_below_excess=1e-18)


def test_weighted_log_area_term_is_the_objectives_quadratic_model_at_the_targets():
    # The area continuation's term w (log e - log e')^2 with w = (e' / e_mean)^2
    # (solve.continuation_area_weights) has (9)'s area term's value, gradient (both 0) and second
    # derivative in log e where every triangle is at its target; both evaluations carry the weights.
    import casadi as ca

    from sphere_nlp.solve import continuation_area_weights

    V, F = ellipsoid(1)
    c = build_connectivity(F, len(V))
    targets = make_targets("original-areas", V, F, c.vertex_degree, angle_weight=0.0, area_weight=1.0)
    weights = continuation_area_weights(targets, "objective")
    assert weights.std() > 0.1 * weights.mean()                 # unequal targets: the weights differ
    angles = np.full((c.n_faces, 3), np.pi / 3)
    lam_g = np.zeros(0)
    diagonals = {}
    for form, evaluation in (("linear", "numpy"), ("log", "numpy"), ("log", "casadi")):
        nlp = AngleNLP(c, targets, "log-chord", area_form=form, evaluation=evaluation,
                       log_area_weights=weights if form == "log" else None)
        x = nlp.pack(angles, targets.excess)
        derivatives = nlp._numpy_problem()[2] if evaluation == "numpy" else nlp._symbolic_problem()[3]
        f, grad = (np.asarray(v.full()).ravel() for v in derivatives["grad_f"](x, ca.DM.zeros(0, 1)))
        hessian = derivatives["hess_lag"](x, ca.DM.zeros(0, 1), 1.0, np.zeros(nlp.n_equalities)).full()
        assert abs(f.item()) < 1e-20 and np.abs(grad).max() < 1e-12
        diagonals[form, evaluation] = np.diag(hessian)[3 * c.n_faces:]
    np.testing.assert_allclose(diagonals["log", "numpy"], diagonals["linear", "numpy"], rtol=1e-12)
    np.testing.assert_allclose(diagonals["log", "casadi"], diagonals["linear", "numpy"], rtol=1e-12)


@pytest.mark.parametrize("mode", ["original-angles", "equal-areas"])
def test_numpy_and_casadi_evaluation_reach_the_same_optimum(mode):
    # IPOPT's iterates depend on the evaluation only through rounding. In the angle mode that means
    # the same path to the same point; the equal-areas optimum of this symmetric ellipsoid is not
    # isolated (the two runs end at different points of equal objective, 65 and 122 iterations).
    V, F = ellipsoid(2)
    c = build_connectivity(F, len(V))
    targets = make_targets(mode, V, F, c.vertex_degree)
    P = V / np.linalg.norm(V, axis=1, keepdims=True)
    angles, excess = spherical_angles(P, F), signed_solid_angles(P, F)
    runs = []
    # Three vertices with independent positions, as solve_angles picks them: the first three lie in
    # one plane through the centre, which left the Jacobian singular, and whether IPOPT's
    # least-squares multipliers then failed depended on rounding (6 against 5 iterations on an
    # AMD EPYC machine, equal on the machine the test was written on).
    dropped = independent_vertices(P)
    for evaluation in ("numpy", "casadi"):
        nlp = AngleNLP(c, targets, "log-chord", dropped_vertices=dropped,
                       obtuse_corners=angles > np.pi / 2, evaluation=evaluation)
        runs.append(nlp.solve(nlp.pack(angles, excess), options={"tol": 1e-10, "print_level": 0, "sb": "yes"}))
    assert all(r.success for r in runs)
    assert abs(runs[0].objective - runs[1].objective) <= 1e-10 * abs(runs[1].objective)
    for run in runs:
        assert np.abs(nlp.evaluate(run.x)[1]).max() < 1e-9
    if mode == "original-angles":
        assert runs[0].iterations == runs[1].iterations
        np.testing.assert_allclose(runs[0].x, runs[1].x, atol=1e-7)


def test_vectorized_sx_function_replays_casadi_exactly():
    import casadi as ca
    from sphere_nlp.nlp import _vectorize

    x, y = ca.SX.sym("x", 3), ca.SX.sym("y")
    expr = ca.vertcat(ca.sin(x[0]) * ca.exp(y) / x[1], ca.log(x[2]) ** 2 - ca.sqrt(x[1]), 1.5,
                      ca.fmax(x[0], y) + ca.cos(x[0] * x[2]))
    f = ca.Function("f", [x, y], [expr])
    rng = np.random.default_rng(0)
    batch = 20000                                  # more than one slice of the evaluation
    X, Y = rng.random((3, batch)) + 0.1, rng.standard_normal((1, batch))
    expected = f.map(batch)(X, Y).full()
    np.testing.assert_allclose(_vectorize(f)(X, Y)[0], expected, rtol=1e-15, atol=1e-15)


def test_obtuse_form_of_the_edge_constraints_is_exact_on_valid_triangulations():
    # At corners flagged obtuse the log-chord form writes sin(alpha) and sin(u) through the other
    # two corners, using (6); on any valid spherical triangulation both forms must agree, also for
    # corners near pi, where the obtuse form is the accurate one.
    V, F = ellipsoid(2)
    c = build_connectivity(F, len(V))
    P = V / np.linalg.norm(V, axis=1, keepdims=True)
    a, b, d = F[0]
    P[a] += 0.99 * ((P[b] + P[d]) / 2 - P[a])         # next to edge bd: a corner of nearly pi
    P /= np.linalg.norm(P, axis=1, keepdims=True)
    angles, excess = spherical_angles(P, F), signed_solid_angles(P, F)
    assert (excess > 0).all() and angles.max() > np.radians(170)
    targets = make_targets("original-angles", V, F, c.vertex_degree)
    plain = AngleNLP(c, targets, "log-chord")
    flagged = AngleNLP(c, targets, "log-chord", obtuse_corners=angles > np.pi / 2)
    x = plain.pack(angles, excess)
    f_plain, g_plain = plain.evaluate(x)
    f_flagged, g_flagged = flagged.evaluate(x)
    assert abs(f_plain - f_flagged) < 1e-12
    np.testing.assert_allclose(g_flagged, g_plain, atol=1e-9)
    assert np.abs(g_flagged).max() < 1e-9


def test_a_run_that_stays_infeasible_is_stopped_as_diverged():
    # The divergence watch in the iteration callback: with a threshold no iterate can meet, the run
    # stops after exactly abort_iterations iterations; the same cached solver without it converges.
    from sphere_nlp import solve

    c, nlp, x = small_log_chord_problem()
    x[:5] += 0.3                                  # infeasible: the first iterates violate (7)-(8)
    seen = []
    run = nlp.solve(x, options=SETTINGS.ipopt_options, abort_violation=1e-300, abort_iterations=3,
                    progress=lambda it, f, viol, elapsed: seen.append(viol))
    assert run.status == "Diverged" and not run.success
    assert len(seen) == 3 and min(seen) > 1e-300
    run = nlp.solve(x, options=SETTINGS.ipopt_options)
    assert run.success and solve.max_constraint_violation(c, *nlp.unpack(run.x)) < 1e-8


def test_captured_output_of_mumps_out_of_memory_is_classified_as_such():
    # IPOPT's own lines when MUMPS cannot allocate its workspace (INFO(1) = -13, the 692k-vertex
    # armadillo with a 34 GB reservation) or still lacks memory after its retries (-8/-9); the run
    # then ended as Restoration_Failed, which said nothing of memory.
    from sphere_nlp.nlp import (LINEAR_SOLVER_FAILED, LINEAR_SOLVER_OUT_OF_MEMORY, _shown, classify_c_output,
                                failure_advice)

    minus13 = (b"   0  6.8522186e+02 1.80e-01 1.28e+00  -6.0 0.00e+00    -  0.00e+00 0.00e+00   0\n"
               b"MUMPS returned INFO(1) =-13 - out of memory when trying to allocate 4225 MB.\n"
               b'In some cases it helps to decrease the value of the option "mumps_mem_percent".\n'
               b"WARNING: Problem in step computation; switching to emergency mode.\n")
    retries = (b"MUMPS returned INFO(1) = -9 and requires more memory, reallocating.  Attempt 20\n"
               b"MUMPS was not able to obtain enough memory.\n")
    assert classify_c_output(minus13) == LINEAR_SOLVER_OUT_OF_MEMORY
    assert classify_c_output(minus13.decode()) == LINEAR_SOLVER_OUT_OF_MEMORY
    assert classify_c_output(retries) == LINEAR_SOLVER_OUT_OF_MEMORY
    assert classify_c_output(b"Error=-13 returned from MUMPS in Factorization.\n") == LINEAR_SOLVER_OUT_OF_MEMORY
    # A retry that got its memory is not a failure, nor is IPOPT's ordinary log.
    assert classify_c_output(retries.splitlines(keepends=True)[0]) is None
    assert classify_c_output(b"iter    objective    inf_pr   inf_du lg(mu)\n") is None
    assert classify_c_output(b"") is None
    # The BLAS refusing its arguments stays a linear-solver failure, and counts first.
    illegal = b" ** On entry to DTRSV parameter number  6 had an illegal value\n"
    assert classify_c_output(illegal) == LINEAR_SOLVER_FAILED
    assert classify_c_output(minus13 + illegal) == LINEAR_SOLVER_FAILED
    # The memory lines become the status, not terminal text; the rest of the log is shown.
    assert [line for line in minus13.splitlines(keepends=True) if _shown(line)] == minus13.splitlines(keepends=True)[::3]
    assert "ran out of memory" in failure_advice(LINEAR_SOLVER_OUT_OF_MEMORY)
    assert failure_advice("Restoration_Failed") is None


def test_a_run_whose_mumps_workspace_is_refused_ends_out_of_memory():
    # MUMPS asked to reserve its estimate plus 2e9 percent (~100 GB on this small problem): Linux
    # refuses the allocation (INFO(1) = -13) at every factorisation, and IPOPT cannot recover.
    c, nlp, x = small_log_chord_problem()
    run = nlp.solve(x, options=dict(SETTINGS.ipopt_options, mumps_mem_percent=2_000_000_000))
    if run.status in ("Solve_Succeeded", "Solved_To_Acceptable_Level"):
        pytest.skip("this machine granted MUMPS a ~100 GB workspace")
    assert run.status == "Linear_Solver_Out_Of_Memory" and not run.success
