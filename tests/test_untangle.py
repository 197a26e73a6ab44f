"""Local untangling of spherical maps: flipped triangles repaired, the rest of the map left exactly as it was."""

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.csgraph import shortest_path

from conftest import shared_mesh
from sphere_nlp.certify import certify, signed_solid_angles
from sphere_nlp.shapes import icosphere
from sphere_nlp.untangle import mean_value_weights, untangle


def unit(X):
    return X / np.linalg.norm(X, axis=1, keepdims=True)


def graph_distance(faces, n, sources):
    """Edge-count distance of every vertex from the nearest source vertex."""
    rows, cols = faces.ravel(), np.roll(faces, -1, axis=1).ravel()
    A = sp.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n)).tocsr()
    return shortest_path(A, unweighted=True, directed=False, indices=sources).min(axis=0)


def fold(V, F, vertices):
    """Reflect each vertex across the great circle through the far edge of one of its triangles."""
    X = V.copy()
    for v in vertices:
        face = F[np.flatnonzero((F == v).any(axis=1))[0]]
        a, b = face[face != v]
        normal = unit(np.cross(V[a], V[b])[None])[0]
        # Reflect, then push a bit further so the folded triangles are clearly flipped, not degenerate.
        X[v] = V[v] - 2.2 * (V[v] @ normal) * normal
    return unit(X)


@pytest.fixture
def folded_icosphere():
    V, F = icosphere(3)                     # 642 vertices; the identity map is valid
    folded = [0, 200, 500]
    return V, F, fold(V, F, folded), folded


def test_folded_vertices_are_untangled_and_far_vertices_stay_put(folded_icosphere):
    V, F, X, folded = folded_icosphere
    before = certify(X, F)
    assert not before.valid and before.flipped >= 3
    Y, info = untangle(X, F, mesh_vertices=V)
    assert Y is not None and certify(Y, F).valid
    assert info.valid and info.flipped_before == before.flipped and info.flipped_after == 0
    # Round r frees the (r - 1)-ring of the flipped triangles' vertices (1-ring of the folded ones),
    # so anything further than r rings from a folded vertex is never free.
    distance = graph_distance(F, len(V), folded)
    far = distance > info.rounds
    assert far.sum() > 0.8 * len(V)
    np.testing.assert_array_equal(Y[far], X[far])
    moved = ~(Y == X).all(axis=1)
    assert info.moved_vertices == moved.sum() and moved[folded].all()
    # The repaired vertices land near where they were before the fold (the icosphere is its own map).
    assert np.max(np.linalg.norm(Y[folded] - V[folded], axis=1)) < 0.1


def test_uniform_weights_also_untangle(folded_icosphere):
    V, F, X, _ = folded_icosphere
    Y, info = untangle(X, F, weights="uniform")
    assert info.valid and certify(Y, F).valid


def test_valid_map_is_returned_unchanged():
    V, F = icosphere(2)
    Y, info = untangle(V, F, mesh_vertices=V)
    np.testing.assert_array_equal(Y, unit(V))
    assert info.valid and info.rounds == 0 and info.moved_vertices == 0


def test_missing_vertex_position_is_filled_in():
    V, F = icosphere(2)
    X = V.copy()
    X[17] = np.nan
    Y, info = untangle(X, F, mesh_vertices=V)
    assert info.valid and np.isfinite(Y).all() and certify(Y, F).valid
    assert np.linalg.norm(Y[17] - V[17]) < 0.05


def test_mirror_image_is_reported_not_untangled():
    # Every triangle is flipped (degree -1): there is no outside to keep, so the call must fail cleanly.
    V, F = icosphere(1)
    Y, info = untangle(V * [-1, 1, 1], F)
    assert Y is None and not info.valid and info.flipped_after == len(F) and info.reason


def test_mean_value_weights_reproduce_a_planar_mesh():
    # Mean-value coordinates are exact for linear functions: each vertex of a flat mesh is the
    # weighted mean of its neighbours.
    rng = np.random.default_rng(1)
    V, F = icosphere(2)
    flat = np.c_[V[:, :2] + 0.01 * rng.standard_normal((len(V), 2)), np.zeros(len(V))]
    upper = V[:, 2] > 0.3                   # a disk of the sphere, flattened; interior vertices only
    W = mean_value_weights(flat, F)
    interior = np.flatnonzero(upper & (np.asarray((W[:, ~upper] > 0).sum(axis=1)).ravel() == 0))
    assert len(interior) > 20
    W = W[interior]
    mean = (W @ flat) / np.asarray(W.sum(axis=1))
    np.testing.assert_allclose(mean, flat[interior], atol=1e-12)


def test_knight_conformal_map_is_untangled():
    # The start the solver would like to use: FLASH, Mobius-centred by vertex area (57 flips).
    from sphere_nlp.conformal import conformal_map
    from sphere_nlp.embedding import mobius_centre
    from sphere_nlp.mesh_io import load_mesh
    from sphere_nlp.repair import prepare_mesh
    from sphere_nlp.starts import vertex_areas

    mesh = prepare_mesh(*load_mesh(shared_mesh("knight.off")))
    V, F = mesh.normalised_vertices, mesh.faces
    X = mobius_centre(conformal_map(V, F), vertex_areas(V, F, len(V)))
    assert (signed_solid_angles(X, F) <= 0).sum() > 10
    Y, info = untangle(X, F, mesh_vertices=V)
    assert info.valid and certify(Y, F).valid
    # Only a neighbourhood of the flips moves.
    assert info.moved_vertices < 0.5 * len(V)


def planar_area(plane, faces):
    """Signed doubled area of planar triangles, positive counter-clockwise."""
    ab, ac = plane[faces[:, 1]] - plane[faces[:, 0]], plane[faces[:, 2]] - plane[faces[:, 0]]
    return ab[:, 0] * ac[:, 1] - ab[:, 1] * ac[:, 0]


def horseshoe_grid():
    """Unit squares of a 6 x 6 grid with a 2-wide slot cut from the top: a non-convex disk."""
    squares = [(i, j) for i in range(6) for j in range(6) if not (2 <= i < 4 and j >= 2)]
    index = lambda i, j: 7 * j + i
    faces = []
    for i, j in squares:
        a, b, c, d = index(i, j), index(i + 1, j), index(i + 1, j + 1), index(i, j + 1)
        faces += [(a, b, c), (a, c, d)]
    faces = np.array(faces)
    used, faces = np.unique(faces, return_inverse=True)
    faces = faces.reshape(-1, 3)
    grid = np.c_[used % 7, used // 7].astype(float)
    return grid, faces


def test_winslow_untangles_a_collapsed_horseshoe():
    # Inside a non-convex boundary Tutte's theorem does not apply; the Winslow untangler (used when a
    # region's Tutte layout has flips) must still find a valid layout, here from every interior vertex
    # piled up near one point, which flips or flattens every interior triangle.
    from sphere_nlp.untangle import _Reference, _winslow_untangle

    grid, faces = horseshoe_grid()
    edges = np.sort(np.r_[faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]], axis=1)
    unique, count = np.unique(edges, axis=0, return_counts=True)
    free = np.setdiff1d(np.arange(len(grid)), unique[count == 1].ravel())
    start = grid.copy()
    start[free] = [1.0, 1.0] + 0.01 * np.random.default_rng(0).standard_normal((len(free), 2))
    reference = _Reference(np.c_[grid, np.zeros(len(grid))], faces)
    plane = _winslow_untangle(start, free, faces, reference.inverse, np.ones(len(faces)), np.ones(len(free)))
    assert plane is not None
    assert (planar_area(plane, faces) > 0).all()
    # With the grid itself as reference the optimum is the grid: the layout comes back close to it.
    assert np.abs(plane - grid).max() < 1e-3


def test_untangle_reports_its_steps(folded_icosphere):
    # A thin limb's collapsed tip can keep the untangling busy for minutes: it reports every region
    # and Winslow step, under the stage name the CLI prints.
    V, F, X, _ = folded_icosphere
    calls = []
    Y, info = untangle(X, F, mesh_vertices=V, progress=lambda *args: calls.append(args))
    assert certify(Y, F).valid
    assert calls and {c[0] for c in calls} == {"start (untangle)"}
    steps = [c[1] for c in calls]
    assert steps == list(range(1, len(steps) + 1))
    assert calls[0][2] == info.flipped_before
    assert all(c[3] == 0.0 and c[4] >= 0 for c in calls)


def test_winslow_gradient_matches_finite_differences():
    from sphere_nlp.untangle import _Reference, _winslow_energy

    grid, faces = horseshoe_grid()
    rng = np.random.default_rng(2)
    plane = grid + 0.3 * rng.standard_normal(grid.shape)      # some triangles flipped
    inverse = _Reference(np.c_[grid, np.zeros(len(grid))], faces).inverse
    weights = rng.uniform(0.5, 2, len(faces))
    args = (faces, inverse, weights, 0.1, 0.9)
    _, grad, det = _winslow_energy(plane, *args)
    assert (det < 0).any()
    step = 1e-6
    numeric = np.zeros_like(plane)
    for index in np.ndindex(*plane.shape):
        up, down = plane.copy(), plane.copy()
        up[index] += step
        down[index] -= step
        numeric[index] = (_winslow_energy(up, *args)[0] - _winslow_energy(down, *args)[0]) / (2 * step)
    np.testing.assert_allclose(grad, numeric, rtol=1e-5, atol=1e-5 * np.abs(numeric).max())


def test_winslow_gives_up_early_where_no_layout_exists():
    # A boundary loop turned clockwise (the horseshoe mirrored, its interior not) admits no layout
    # with every triangle positive: the untangler must say so once its updates stop removing
    # inverted triangles, not after all of them (a thin tail's tip cost 28 s a round that way).
    from sphere_nlp.untangle import _Reference, _winslow_untangle

    grid, faces = horseshoe_grid()
    edges = np.sort(np.r_[faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]], axis=1)
    unique, count = np.unique(edges, axis=0, return_counts=True)
    boundary = np.unique(unique[count == 1].ravel())
    free = np.setdiff1d(np.arange(len(grid)), boundary)
    start = grid.copy()
    start[boundary, 0] = 6 - start[boundary, 0]
    reference = _Reference(np.c_[grid, np.zeros(len(grid))], faces)
    steps = {}
    for stalled in (3, 13):
        ticks = []
        plane = _winslow_untangle(start, free, faces, reference.inverse, np.ones(len(faces)), np.ones(len(free)),
                                  tick=lambda: ticks.append(1), max_stalled_updates=stalled)
        assert plane is None
        steps[stalled] = len(ticks)
    assert steps[3] < steps[13]

