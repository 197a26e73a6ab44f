"""Starting points (sphere_nlp.starts): the linear guess, the valid starts and their Mobius gauge, given positions."""

import numpy as np
import pytest

from sphere_nlp.certify import certify, signed_solid_angles
from sphere_nlp.connectivity import build_connectivity
from sphere_nlp import starts
from sphere_nlp.solve import constraint_residuals
from sphere_nlp.starts import linear_initial_guess
from sphere_nlp.targets import MODES, make_targets

from meshgen import ellipsoid


@pytest.mark.parametrize("mode", MODES)
def test_linear_initial_guess_satisfies_linear_constraints(mode):
    V, F = ellipsoid(2)
    c = build_connectivity(F, len(V))
    angles, excess = linear_initial_guess(c, make_targets(mode, V, F, c.vertex_degree))
    res = constraint_residuals(c, angles, excess)
    assert np.abs(res["triangle"]).max() < 1e-12
    assert np.abs(res["vertex"]).max() < 1e-12


def test_excess_gauge_is_stationary_for_sum_of_squared_excesses_and_stays_valid():
    from sphere_nlp import solve
    from sphere_nlp.certify import certify, signed_solid_angles
    from sphere_nlp.embedding import excess_gauge, mobius_centre

    V, F = ellipsoid(2, axes=(1.0, 3.0, 0.4))
    c = build_connectivity(F, len(V))
    area_centred, _ = starts.starting_positions(c, V)
    pushed = mobius_centre(area_centred, np.where(area_centred[:, 0] > 0, 30.0, 1.0))  # off-centre
    moved = excess_gauge(pushed, F)

    def weighted_mean(X):     # the gradient of sum(e^2) over Mobius boosts, up to a factor
        e = signed_solid_angles(X, F)
        centres = X[F].sum(1)
        centres /= np.linalg.norm(centres, axis=1, keepdims=True)
        return (e * e) @ centres / (e @ e), e @ e

    (g_before, f_before), (g_after, f_after) = weighted_mean(pushed), weighted_mean(moved)
    assert certify(moved, F).valid
    assert f_after < f_before and np.linalg.norm(g_before) > 0.04
    assert np.linalg.norm(g_after) < 0.2 * np.linalg.norm(g_before)   # first order only on coarse meshes


def test_initial_points_are_valid_triangulations_and_given_positions_are_checked():
    # Every named valid start certifies and its angles satisfy (6) and (7) to rounding; positions
    # the caller gives are used as they are if they certify, refused with a UsageError if not.
    from sphere_nlp.errors import UsageError

    V, F = ellipsoid(2, axes=(1.0, 2.0, 0.7))
    c = build_connectivity(F, len(V))
    targets = make_targets("original-angles", V, F, c.vertex_degree)
    for start, kind in (("auto", "conformal"), ("embedding", "embedding")):
        point = starts.initial_point(c, targets, start, V)
        assert point.kind.startswith(kind) and certify(point.positions, F).valid
        residuals = constraint_residuals(c, point.angles, point.excess)
        assert np.abs(residuals["triangle"]).max() < 1e-12 and np.abs(residuals["vertex"]).max() < 1e-12
    given = starts.initial_point(c, targets, point.positions, V)
    assert given.kind == "given" and np.array_equal(given.positions, point.positions)
    with pytest.raises(UsageError, match="not a valid spherical map"):
        starts.initial_point(c, targets, point.positions * [-1, 1, 1], V)      # mirrored: every face flipped
    linear = starts.initial_point(c, targets, "linear")
    assert linear.kind == "linear" and linear.positions is None
    np.testing.assert_allclose(constraint_residuals(c, linear.angles, linear.excess)["vertex"], 0, atol=1e-10)


def test_a_degree_1000_cap_gets_a_valid_start_with_its_ring_on_the_equator():
    from meshgen import bipyramid
    from sphere_nlp.embedding import convex_embedding, punctured_embedding

    V, F = bipyramid(1000)
    c = build_connectivity(F, len(V))
    # The triangle-bounded embedding loses the ring to floating point ...
    assert not certify(convex_embedding(c, V, weights="uniform"), F).valid
    # ... the one around the apex places it exactly: apexes at the poles, the ring on the equator.
    X = punctured_embedding(c)
    assert certify(X, F).valid
    assert np.allclose(np.abs(X[1000:, 2]), 1.0) and np.abs(X[:1000, 2]).max() < 1e-12
    positions, kind = starts.starting_positions(c, V)
    assert certify(positions, F).valid and kind.startswith("embedding")


def test_conformal_map_of_the_surfaces_own_angles_is_the_surfaces_map():
    # Cotangents and Beltrami coefficients need only each triangle's shape, so rebuilding the
    # triangles from their angles (each at its own size and place) gives the same map.
    from sphere_nlp.conformal import conformal_map
    from sphere_nlp.geometry import corner_angles
    from meshgen import random_genus0_mesh

    V, F = random_genus0_mesh(300, seed=3)
    V = V * [1.0, 2.5, 0.6]
    assert np.abs(conformal_map(V, F, angles=corner_angles(V, F)) - conformal_map(V, F)).max() < 1e-9


def test_equal_angles_start_from_the_map_conformal_to_their_targets():
    # A long ellipsoid: its surface's conformal map is far from equal angles, the map conformal to
    # the 2 pi / deg targets' metric is close (4 iterations against 9 from the surface's map), and
    # both reach the same optimum.
    import sphere_nlp
    from sphere_nlp.geometry import corner_angles, spherical_angles

    V, F = ellipsoid(2, axes=(1.0, 4.0, 0.5))
    c = build_connectivity(F, len(V))
    targets = make_targets("equal-angles", V, F, c.vertex_degree)
    point = starts.initial_point(c, targets, "auto", V)
    surface, _ = starts.starting_positions(c, V)
    assert certify(point.positions, F).valid
    to_targets = np.abs(point.angles - targets.angles).mean()
    assert to_targets < 0.5 * np.abs(spherical_angles(surface, F) - targets.angles).mean()
    # the original modes' targets are the surface's angles: the surface's own map, as before
    own = make_targets("original-angles", V, F, c.vertex_degree)
    assert np.allclose(own.angles, corner_angles(V, F))
    assert starts._metric_angles(c, own, V) is None and starts._metric_angles(c, targets, V) is targets.angles
    # equal-areas has the same angle targets, so the same metric; original-areas the surface's
    equal_areas = make_targets("equal-areas", V, F, c.vertex_degree)
    assert starts._metric_angles(c, equal_areas, V) is equal_areas.angles
    assert starts._metric_angles(c, make_targets("original-areas", V, F, c.vertex_degree), V) is None
    from_metric = sphere_nlp.parameterize((V, F), "equal-angles")
    from_surface = sphere_nlp.parameterize((V, F), "equal-angles", start=surface)
    assert from_metric.certificate.valid and from_surface.certificate.valid
    assert from_metric.iterations < from_surface.iterations
    assert abs(from_metric.objective - from_surface.objective) <= 1e-8 * from_surface.objective


def test_equal_areas_walks_from_its_targets_metric_to_the_same_or_a_lower_optimum():
    # The long ellipsoid's surface map crowds its ends; the map of the 2 pi / deg metric does not,
    # so equal-areas needs a shorter walk and fewer iterations (13 against 83) to the same optimum;
    # on the tentacle creature it ends lower (25.93 against 28.54).
    import sphere_nlp
    from meshgen import tentacle_creature

    for (V, F), fewer in (((ellipsoid(3, axes=(1.0, 4.0, 0.5))), True), (tentacle_creature(), False)):
        surface, _ = starts.starting_positions(build_connectivity(F, len(V)), V)
        from_metric = sphere_nlp.parameterize((V, F), "equal-areas", start="conformal")
        from_surface = sphere_nlp.parameterize((V, F), "equal-areas", start=surface)
        assert from_metric.certificate.valid and from_surface.certificate.valid
        assert from_metric.objective <= from_surface.objective * (1 + 1e-8)
        if fewer:
            assert from_metric.iterations < 0.5 * from_surface.iterations


def test_the_start_names_each_of_its_parts_to_the_progress_function():
    # At 700k vertices the conformal map and the gauge take tens of seconds each: a run's progress
    # says which one runs, in order, with the seconds since the start began.
    V, F = ellipsoid(2)
    c = build_connectivity(F, len(V))
    calls = []
    positions, kind = starts.starting_positions(c, V, gauge="excess", progress=lambda *args: calls.append(args))
    assert certify(positions, F).valid and kind == "conformal"
    assert [call[0] for call in calls] == ["start (conformal map)", "start (Mobius gauge)"]
    assert all(call[4] >= 0 for call in calls)


def test_the_meshs_vertex_order_is_computed_once_and_orders_flashs_solves(monkeypatch):
    # Connectivity.vertex_order: METIS on the edge graph, kept; FLASH's two Dirichlet solves restrict
    # it to their free vertices (from conformal.NESTED_DISSECTION_UNKNOWNS, lowered here) and solve
    # the same systems as with SuperLU's own order.
    from sphere_nlp import conformal, sparse_lu
    from sphere_nlp.connectivity import vertex_graph
    from sphere_nlp.shapes import icosphere

    V, F = icosphere(4)
    V = V * [1.0, 1.3, 0.8]
    C = build_connectivity(F, len(V))
    order = C.vertex_order()
    assert order is C.vertex_order() and sorted(order.tolist()) == list(range(len(V)))
    assert np.array_equal(order, sparse_lu.nested_dissection(vertex_graph(F, len(V))))
    orderings = []
    factorize = sparse_lu.factorize
    monkeypatch.setattr(sparse_lu, "factorize", lambda A, ordering=None, **kw: (
        orderings.append(ordering), factorize(A, ordering=ordering, **kw))[1])
    monkeypatch.setattr(conformal, "NESTED_DISSECTION_UNKNOWNS", 0)
    shared = conformal.conformal_map(V, F, vertex_order=order)
    assert len(orderings) == 2 and all(o is not None and len(o) < len(V) for o in orderings)
    # Without an order given, the map orders its solves from the faces, the same way.
    assert np.array_equal(conformal.conformal_map(V, F), shared)
    monkeypatch.setattr(conformal, "NESTED_DISSECTION_UNKNOWNS", 10 ** 9)
    own = conformal.conformal_map(V, F)
    assert orderings[-1] is None
    assert np.abs(shared - own).max() < 1e-9 and certify(shared, F).valid


def _fold_the_embeddings(monkeypatch, V):
    """Make the convex and the punctured embedding of (V, ...) come out folded: one vertex thrown
    across the sphere, as rounding does to parts too thin for double precision."""
    import sphere_nlp.embedding as embedding

    def folded(*args, **keywords):
        X = V / np.linalg.norm(V, axis=1, keepdims=True)
        X[0] = -X[0]
        return X

    monkeypatch.setattr(embedding, "convex_embedding", folded)
    monkeypatch.setattr(embedding, "punctured_embedding", folded)


def test_an_embedding_rounded_to_an_invalid_map_says_so(monkeypatch):
    # The convex embedding is valid in exact arithmetic; where rounding breaks it (parts too thin for
    # double precision) and the punctured embedding fails as well, the start is named as invalid
    # instead of passing for a certified one.
    V, F = ellipsoid(1)
    connectivity = build_connectivity(F, len(V))
    positions, kind = starts.embedding_start(connectivity, V)
    assert kind in ("embedding", "embedding-uncentred") and certify(positions, F).valid

    _fold_the_embeddings(monkeypatch, V)
    positions, kind = starts.embedding_start(connectivity, V)
    assert kind == "embedding-invalid" and not certify(positions, F).valid
    _, kind = starts.starting_positions(connectivity, V, kind="embedding")
    assert kind == "embedding-invalid"


def test_a_target_metric_that_cannot_be_untangled_falls_back_on_the_surfaces_conformal_map(monkeypatch):
    # A thin body's map to the 2 pi / deg metric can stay folded after untangling where the
    # surface's own conformal map does not: the start is then the surface's map, named so.
    V, F = ellipsoid(1)
    connectivity = build_connectivity(F, len(V))
    surface, kind = starts.starting_positions(connectivity, V)
    assert kind == "conformal"
    real = starts.conformal_start
    monkeypatch.setattr(starts, "conformal_start",
                        lambda c, v, w=None, angles=None, *rest: None if angles is not None else real(c, v, w, None, *rest))
    equal = make_targets("equal-angles", V, F, connectivity.vertex_degree)
    positions, kind = starts.starting_positions(connectivity, V, angles=equal.angles)
    assert kind == "surface-conformal" and certify(positions, F).valid
    assert np.array_equal(positions, surface)


def test_no_valid_start_is_a_failure_named_before_any_solving(monkeypatch):
    # Folded start angles (negative excesses) would reach IPOPT as logarithms of negative numbers:
    # the solve stops at once with its own status, and the run says why.
    import warnings
    import sphere_nlp
    from sphere_nlp.errors import SolveError

    V, F = ellipsoid(1)
    monkeypatch.setattr(starts, "conformal_start", lambda *args, **keywords: None)
    _fold_the_embeddings(monkeypatch, V)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        result = sphere_nlp.parameterize((V, F), target="equal-angles", check=False)
        assert not result.success and result.status == "No_Valid_Start" and result.iterations == 0
        assert result.start == "embedding-invalid" and result.stages == []
        with pytest.raises(SolveError, match="no valid starting map"):
            sphere_nlp.parameterize((V, F))
