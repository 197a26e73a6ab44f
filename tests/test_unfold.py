"""Unfolding without drift: the walk's error, the correction, slivers, noisy angles, the report.

The NLP cannot run at 10k-50k vertices in a test, so the inputs are spherical meshes whose angles are
known: points on the unit sphere, triangulated, angles measured from them (optionally perturbed to
emulate a solver's tolerance). The unfolded positions must reproduce those angles.
"""

import time

import numpy as np
import pytest
from scipy.spatial import ConvexHull

import sphere_nlp
from sphere_nlp.certify import certify, spherical_angles
from sphere_nlp.connectivity import build_connectivity
from sphere_nlp.shapes import cylinder, icosphere
from sphere_nlp.unfold import angle_gradients, central_face, correct, tangent_bases, unfold, walk


def hull_mesh(points):
    """Convex hull of points on the unit sphere, faces oriented outward."""
    faces = ConvexHull(points).simplices
    a, b, c = (points[faces[:, k]] for k in range(3))
    inward = np.einsum("ij,ij->i", a, np.cross(b, c)) < 0
    faces[inward] = faces[inward][:, ::-1]
    return points, faces


def random_sphere_mesh(n, seed=0):
    """Convex hull of n random unit vectors: a Delaunay mesh with many thin triangles."""
    points = np.random.default_rng(seed).normal(size=(n, 3))
    return hull_mesh(points / np.linalg.norm(points, axis=1, keepdims=True))


def jittered_icosphere(subdivisions, jitter=0.08, seed=0):
    """Icosphere with vertices moved along the sphere by ``jitter`` times the mean edge length."""
    V, F = icosphere(subdivisions)
    rng = np.random.default_rng(seed)
    V = V + jitter * np.sqrt(4 * np.pi / len(F)) * rng.normal(size=V.shape)
    return V / np.linalg.norm(V, axis=1, keepdims=True), F


def needle_mesh(subdivisions, count, gap, seed=0):
    """Jittered icosphere plus ``count`` twin points at ``gap`` times the edge length from a vertex.

    Each twin makes a short edge whose triangles have an angle of about ``gap`` radians opposite it.
    """
    V, _ = jittered_icosphere(subdivisions, seed=seed)
    rng = np.random.default_rng(seed + 1)
    h = np.sqrt(2 * np.pi / len(V))
    pick = rng.choice(len(V), count, replace=False)
    step = rng.normal(size=(count, 3))
    step -= np.einsum("ij,ij->i", step, V[pick])[:, None] * V[pick]
    twins = V[pick] + gap * h * step / np.linalg.norm(step, axis=1, keepdims=True)
    return hull_mesh(np.vstack([V, twins / np.linalg.norm(twins, axis=1, keepdims=True)]))


def band_mesh(fine=1000, coarse=12, gap=0.5, seed=0):
    """A dense cap, a ring of ``fine`` points at its edge, a ring of ``coarse`` points ``gap`` radians
    further south, and a sparse south: the strip between the rings is fans of needles whose sharp
    corners (about 0.007 rad) sit at the coarse ring's vertices, the only way the walk can reach them.
    """
    rng = np.random.default_rng(seed)

    def ring(count, z, phase):
        phi = 2 * np.pi * (np.arange(count) + phase) / count
        return np.c_[np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), np.full(count, z)]

    points = rng.normal(size=(6000, 3))
    points /= np.linalg.norm(points, axis=1, keepdims=True)
    z_fine, z_coarse = 0.3, np.cos(np.arccos(0.3) + gap)
    return hull_mesh(np.vstack([points[points[:, 2] > z_fine + 0.05][:2000], ring(fine, z_fine, 0),
                                ring(coarse, z_coarse, 0.5), points[points[:, 2] < z_coarse - 0.3][:200]]))


def exact_problem(V, F, noise=0.0, seed=3):
    """Connectivity and the angles of the spherical mesh, relatively perturbed by up to ``noise``."""
    angles = spherical_angles(V, F)
    assert (angles > 0).all()
    if noise:
        angles = angles * (1 + noise * np.random.default_rng(seed).uniform(-1, 1, angles.shape))
    return build_connectivity(F, len(V)), angles


def max_angle_error(X, F, angles):
    return float(np.abs(spherical_angles(X, F) - angles).max())


def test_angle_gradients_match_finite_differences():
    V, F = jittered_icosphere(1, jitter=0.3)
    G, T = angle_gradients(V, F), tangent_bases(V)
    rng = np.random.default_rng(1)
    step = 1e-7
    for _ in range(20):
        face, slot, direction = rng.integers(len(F)), rng.integers(3), rng.integers(2)
        vertex = F[face, slot]
        moved = [V.copy(), V.copy()]
        for sign, X in zip((1, -1), moved):
            X[vertex] = V[vertex] + sign * step * T[vertex][:, direction]
            X[vertex] /= np.linalg.norm(X[vertex])
        numeric = (spherical_angles(moved[0], F)[face] - spherical_angles(moved[1], F)[face]) / (2 * step)
        np.testing.assert_allclose(G[face, :, slot] @ T[vertex][:, direction], numeric, atol=1e-7)


def test_plain_walk_drifts_with_depth_and_correction_removes_it():
    # The paper's caveat, measured: with exact angles the plain breadth-first walk's error grows with
    # its depth (about 30x per doubling); the Gauss-Newton correction takes it to rounding level.
    walk_error = {}
    for subdivisions in (3, 5):
        V, F = jittered_icosphere(subdivisions)
        connectivity, angles = exact_problem(V, F)
        X, levels, _ = walk(connectivity, angles, central_face(connectivity), repair=False)
        walk_error[subdivisions] = max_angle_error(X, F, angles)
    assert len(V) == 10242
    assert walk_error[5] > 1e-9
    assert walk_error[5] > 100 * walk_error[3]

    start = time.perf_counter()
    X, info = unfold(connectivity, angles)
    elapsed = time.perf_counter() - start
    assert info["walk_repairs"] == 0                     # well-shaped: the walk needs no repair
    assert info["walk_max_angle_error"] == pytest.approx(walk_error[5])
    assert info["corrected_max_angle_error"] < 1e-11
    assert info["corrected_max_angle_error"] < 1e-3 * info["walk_max_angle_error"]
    assert info["corrected_rms_angle_error"] < info["walk_rms_angle_error"]
    assert max_angle_error(X, F, angles) == pytest.approx(info["corrected_max_angle_error"])
    assert certify(X, F).valid
    assert elapsed < 10


@pytest.mark.parametrize("average", [True, False])
def test_needle_triangles(average):
    # Twins at 1e-3 of an edge length: angles down to ~0.03 degrees, some near 135 degrees, and
    # triangles far smaller than the rest, whose excess carries no usable scale.
    V, F = needle_mesh(4, count=100, gap=1e-3)
    connectivity, angles = exact_problem(V, F, noise=1e-9)
    assert np.degrees(angles.min()) < 0.1
    X, info = unfold(connectivity, angles, average=average)
    assert info["corrected_max_angle_error"] < 1e-7
    assert info["corrected_max_angle_error"] <= info["walk_max_angle_error"]
    assert certify(X, F).valid


@pytest.mark.parametrize("noise", [1e-9, 1e-7])
def test_noisy_angles_on_random_mesh(noise):
    # Angles off by up to `noise` (relative) cannot all be met; the fit lands at the noise level.
    V, F = random_sphere_mesh(5000, seed=2)
    connectivity, angles = exact_problem(V, F, noise=noise)
    X, info = unfold(connectivity, angles)
    assert info["corrected_max_angle_error"] < 10 * noise
    assert info["corrected_rms_angle_error"] < 2 * noise
    assert certify(X, F).valid


def test_correct_fits_a_sub_mesh_and_leaves_other_vertices_alone():
    V, F = jittered_icosphere(2)
    angles = spherical_angles(V, F)
    rng = np.random.default_rng(4)
    start = V + 1e-4 * rng.normal(size=V.shape)
    part = np.arange(len(F) // 2)
    X, stats = correct(F[part], angles[part], start)
    assert max_angle_error(X, F[part], angles[part]) < 1e-12
    untouched = np.setdiff1d(np.arange(len(V)), F[part])
    np.testing.assert_array_equal(X[untouched], start[untouched])
    assert stats["factorizations"] >= 1


def test_without_correction_the_walk_is_returned():
    V, F = jittered_icosphere(3)
    connectivity, angles = exact_problem(V, F)
    X, info = unfold(connectivity, angles, correction=False, seed_face=0)
    assert info["seed_face"] == 0
    assert "corrected_max_angle_error" not in info
    assert max_angle_error(X, F, angles) == pytest.approx(info["walk_max_angle_error"])


def test_report_has_unfold_errors_before_and_after_correction():
    report = sphere_nlp.parameterize(cylinder(), target="equal-angles").report()
    unfold_report = report["unfold"]
    for stage in ("walk", "corrected"):
        for key in ("max_angle_error", "rms_angle_error", "max_chord_mismatch"):
            assert isinstance(unfold_report["%s_%s" % (stage, key)], float)
    assert unfold_report["corrected_max_angle_error"] <= unfold_report["walk_max_angle_error"]
    assert report["max_angle_error"] == pytest.approx(unfold_report["corrected_max_angle_error"], abs=1e-15)


def test_correction_factorises_once_and_reuses_it_to_the_floor():
    # After the first step, the steps solve the current normal equations by conjugate gradients
    # preconditioned with the one factorisation, and reach the angles' own noise level certified.
    V, F = jittered_icosphere(5)
    connectivity, angles = exact_problem(V, F, noise=1e-10)
    X, info = unfold(connectivity, angles)
    assert info["walk_max_angle_error"] > 1e-4                   # a real drift to remove
    assert info["correction_factorizations"] == 1
    assert info["correction_iterations"] >= 2 and info["correction_cg_iterations"] >= 1
    assert info["corrected_max_angle_error"] < 1e-9
    assert max_angle_error(X, F, angles) == pytest.approx(info["corrected_max_angle_error"], abs=1e-15)
    assert certify(X, F).valid


@pytest.mark.parametrize("target", ["original-angles", "original-areas"])
def test_report_timings_name_the_stages_and_their_parts(target):
    # The stages add up to the total, and each stage's parts (``stage.part``) add up to it: the
    # start, IPOPT and (area modes) the authalic map within the solve; the walk and the correction
    # within the unfold.
    timings = sphere_nlp.parameterize(cylinder(), target=target).report()["timings_s"]
    stages = ["load", "build", "solve", "unfold", "certify"]
    parts = {"solve": ["solve.start", "solve.ipopt", "solve.other"]
             + (["solve.authalic"] if target == "original-areas" else []),
             "unfold": [] if target == "original-areas" else ["unfold.walk", "unfold.correction", "unfold.other"]}
    assert set(timings) == set(stages) | {"total"} | set(parts["solve"]) | set(parts["unfold"])
    assert all(value >= 0 for value in timings.values())
    assert sum(timings[k] for k in stages) == pytest.approx(timings["total"], abs=1e-4)
    for stage, names in parts.items():
        if names:
            assert sum(timings[k] for k in names) == pytest.approx(timings[stage], abs=1e-5)
    assert timings["solve.ipopt"] > 0 and timings["solve.start"] > 0     # the start is timed itself


def test_correction_stops_at_the_floor_of_angles_no_positions_have():
    # Slow progress above SLOW_TARGET keeps the correction going (armadillo.obj equal-areas: 1.4e-5
    # -> 8.8e-8 rad); angles off by 1e-6 or 1e-5 from any positions have a floor above it, where
    # the correction must still stop after a few steps instead of running to its iteration limit.
    V, F = icosphere(3)
    rng = np.random.default_rng(1)
    exact = spherical_angles(V, F)
    for noise in (1e-6, 1e-5):
        noisy = exact + noise * rng.normal(size=exact.shape)
        X, stats = correct(F, noisy, V + 1e-3 * rng.normal(size=V.shape))
        assert stats["iterations"] <= 10
        assert max_angle_error(X, F, noisy) < 5 * noise          # the least-squares floor, not a stall
        assert certify(X / np.linalg.norm(X, axis=1, keepdims=True), F).valid


@pytest.mark.slow
@pytest.mark.parametrize("mesh", ["random", "needles"])
def test_large_meshes_reach_the_angles(mesh):
    # >= 50k vertices: a random hull (angles down to 0.017 degrees, excesses down to 1e-8) with
    # angles perturbed at a solver's tolerance, and a jittered icosphere with 10k needles.
    if mesh == "random":
        V, F = random_sphere_mesh(50000)
        connectivity, angles = exact_problem(V, F, noise=1e-10)
    else:
        V, F = needle_mesh(6, count=10000, gap=1e-3)
        connectivity, angles = exact_problem(V, F)
    assert len(V) >= 50000
    X, info = unfold(connectivity, angles)
    assert info["corrected_max_angle_error"] < 1e-7
    assert certify(X, F).valid


def test_walk_repairs_before_crossing_a_band_of_needles(monkeypatch):
    # The coarse ring's vertices can only be placed from needles with 0.007-rad corners at them, which
    # multiply the error of everything placed so far by ~1 / 0.007. Angles off by 1e-6 (a loose
    # solver) leave ~1e-6 of drift before the band: crossing it as is, the walk ends 8e-4 off; with
    # the repair before the band (WALK_FORCED_REPAIR_ERROR), at the level of the angles' own error.
    # (The Loop armadillo's original-areas map: 2 pi and 41 flips without it, certified with it.)
    import sphere_nlp.unfold as unfold_module

    V, F = band_mesh()
    connectivity, angles = exact_problem(V, F, noise=1e-6)
    assert angles.min() < 0.01
    walks, default = {}, unfold_module.WALK_FORCED_REPAIR_ERROR
    for threshold in (default, np.inf):
        monkeypatch.setattr(unfold_module, "WALK_FORCED_REPAIR_ERROR", threshold)
        X, info = unfold(connectivity, angles)
        walks[threshold] = info["walk_max_angle_error"]
        assert certify(X, F).valid and info["corrected_max_angle_error"] < 1e-5
    assert walks[np.inf] > 1e-4
    assert walks[default] < 1e-5


def _coo_normal_matrix(J, faces, n, damping):
    """The normal matrix summed by scipy from the 36 entries of every face (the reference)."""
    import scipy.sparse as sp

    unknowns = (2 * faces[:, :, None] + np.arange(2)).reshape(len(faces), 6)
    blocks = np.einsum("tri,trj->tij", J, J)
    rows = np.broadcast_to(unknowns[:, :, None], blocks.shape).ravel()
    cols = np.broadcast_to(unknowns[:, None, :], blocks.shape).ravel()
    H = sp.csc_matrix((blocks.ravel(), (rows, cols)), shape=(2 * n, 2 * n))
    diag = H.diagonal()
    return H + sp.diags(damping * diag + 1e-12 * diag.mean(), format="csc")


def test_normal_matrix_is_the_sum_of_the_face_blocks():
    from sphere_nlp.unfold import _angle_jacobian, normal_matrix

    V, F = random_sphere_mesh(500)
    X = V / np.linalg.norm(V, axis=1, keepdims=True)
    J, _ = _angle_jacobian(X, F, tangent_bases(X))
    H, reference = normal_matrix(J, F, len(V), 1e-3), _coo_normal_matrix(J, F, len(V), 1e-3)
    assert H.has_canonical_format and H.nnz == reference.nnz
    assert abs(H - reference).max() <= 1e-14 * abs(reference).max()


@pytest.mark.parametrize("ordering", ["metis", "vertex nested dissection"])
def test_ordered_factorisation_solves_like_the_default(ordering):
    # Pre-ordering (nested dissection, then SuperLU in natural order) changes the factors, not the
    # solution: a symmetric positive definite normal matrix, solved both ways, one and several
    # right-hand sides, in the matrix's own numbering.
    from sphere_nlp import sparse_lu
    from sphere_nlp.connectivity import vertex_graph
    from sphere_nlp.unfold import _angle_jacobian, normal_matrix

    V, F = random_sphere_mesh(2000)
    n = len(V)
    X = V / np.linalg.norm(V, axis=1, keepdims=True)
    J, _ = _angle_jacobian(X, F, tangent_bases(X))
    H = normal_matrix(J, F, n, 1e-2)
    if ordering == "metis":
        options = {}
    else:
        perm = sparse_lu.nested_dissection(vertex_graph(F, n))
        options = dict(permc_spec="NATURAL")
        ordering = (2 * perm[:, None] + np.arange(2)).ravel()
    rhs = np.random.default_rng(1).normal(size=(2 * n, 3))
    symmetric = dict(diag_pivot_thresh=0.0, options=dict(SymmetricMode=True))
    default = sparse_lu.factorize(H, permc_spec="MMD_AT_PLUS_A", **symmetric)
    ordered = sparse_lu.factorize(H, ordering=ordering, **options, **symmetric)
    assert ordered.perm is not None and sorted(ordered.perm) == list(range(2 * n))
    for b in (rhs[:, 0], rhs):
        x, y = default.solve(b), ordered.solve(b)
        assert np.abs(H @ y - b).max() < 1e-10 * np.abs(b).max()
        assert np.abs(x - y).max() < 1e-9 * np.abs(x).max()
    with pytest.raises(sparse_lu.NonFiniteSystem):
        ordered.solve(np.full(2 * n, np.nan))


def test_nested_dissection_ordering_reaches_the_same_positions(monkeypatch):
    # The correction's ordering changes rounding only: forced on a small mesh, the unfold matches.
    import sphere_nlp.unfold as unfold_module

    V, F = jittered_icosphere(4)
    connectivity, angles = exact_problem(V, F, noise=1e-10)
    positions = {}
    for threshold in (10 ** 9, 0):
        monkeypatch.setattr(unfold_module, "NESTED_DISSECTION_VERTICES", threshold)
        positions[threshold], info = unfold(connectivity, angles)
        assert info["correction_factorizations"] >= 1 and info["corrected_max_angle_error"] < 1e-9
    assert np.abs(positions[0] - positions[10 ** 9]).max() < 1e-12


def test_corrections_share_one_nested_dissection_order_restricted_to_their_part(monkeypatch):
    # A walk's repair corrects part of the mesh and the final correction all of it: both order their
    # unknowns from the whole mesh's nested dissection (one METIS call), restricted to their part,
    # and reach the same positions as when the part is ordered afresh.
    from sphere_nlp import unfold as U
    from sphere_nlp.certify import spherical_angles
    from sphere_nlp.shapes import icosphere

    monkeypatch.setattr(U, "NESTED_DISSECTION_VERTICES", 100)
    V, F = icosphere(3)
    order = build_connectivity(F, len(V)).vertex_order()
    assert sorted(order.tolist()) == list(range(len(V)))
    part = F[: 2 * len(F) // 3]
    used = np.unique(part)
    local = U._used_order(order, used)
    assert sorted(local.tolist()) == list(range(len(used)))
    assert np.array_equal(used[local], order[np.isin(order, used)])      # the whole order, kept
    rng = np.random.default_rng(1)
    nudged = V + 1e-4 * rng.normal(size=V.shape)
    A = spherical_angles(V, part)
    fresh, fresh_stats = U.correct(part, A, nudged)
    shared, stats = U.correct(part, A, nudged, vertex_order=order)
    assert stats["max_angle_error"] < 1e-12 and fresh_stats["max_angle_error"] < 1e-12
    # The same shape; the rotations (the null space, held by a 1e-12 damping) may differ by rounding.
    u, _, vt = np.linalg.svd(shared[used].T @ fresh[used])
    assert np.abs(shared[used] @ (u @ vt) - fresh[used]).max() < 1e-10
    assert np.array_equal(shared[np.setdiff1d(np.arange(len(V)), used)], nudged[np.setdiff1d(np.arange(len(V)), used)])
