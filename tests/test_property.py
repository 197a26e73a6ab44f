"""Property tests on random closed genus-0 meshes: every run is certified or a clean, documented failure.

The meshes (tests/meshgen.py: ``random_genus0_mesh``) are convex hulls of random points on the sphere,
made non-convex and irregular by radial jitter and random edge flips (a flip is made only when the mesh
stays simple and manifold and both new triangles keep every angle above ~1 degree).

"Clean failure" means :class:`SolveError` or :class:`CertificateError` with a one-line message and
the partial result attached; any other exception fails the test, and so does a result that claims
success without a valid certificate.

Set ``SPHERE_NLP_PROPERTY_LOG=path`` to append one JSON line per example (mesh parameters, status,
iterations, seconds) for statistics on how often and why the solver gives up.
"""

import json
import os
import time

import numpy as np
import pytest

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, example, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

import sphere_nlp  # noqa: E402
from sphere_nlp import errors  # noqa: E402

import meshgen  # noqa: E402

TARGETS = ("equal-angles", "original-angles")

# IPOPT limits per stage. Most random meshes solve in a few dozen iterations and well under a second;
# those IPOPT cannot solve may take thousands of slow (20-40 ms) iterations to give up. The default run
# caps them to stay fast; hitting a cap is a clean SolveError like any other failure, so the property
# tested is the same, only more failures are tolerated. The slow suite uses the package's default
# iteration limit (3000) with a 120 s safety cap per stage.
DEFAULT_LIMITS = dict(max_iter=200, max_time=0.5)
SLOW_LIMITS = dict(max_iter=3000, max_time=120.0)


@st.composite
def random_meshes(draw, max_vertices=60):
    """(n_points, seed, n_flips, jitter) for :func:`meshgen.random_genus0_mesh`."""
    n_points = draw(st.integers(8, max_vertices))
    seed = draw(st.integers(0, 2 ** 32 - 1))
    n_flips = draw(st.integers(0, 2 * n_points))
    jitter = draw(st.sampled_from([0.0, 0.1, 0.3]))
    return n_points, seed, n_flips, jitter


def _log(record):
    path = os.environ.get("SPHERE_NLP_PROPERTY_LOG")
    if path:
        with open(path, "a") as log:
            log.write(json.dumps(record) + "\n")


def check_certified_or_clean_failure(mesh_parameters, target, limits):
    n_points, seed, n_flips, jitter = mesh_parameters
    V, F = meshgen.random_genus0_mesh(n_points, seed, n_flips=n_flips, jitter=jitter)
    record = dict(n_points=n_points, seed=seed, n_flips=n_flips, jitter=jitter, target=target, **limits)
    start = time.perf_counter()
    try:
        result = sphere_nlp.parameterize((V, F), target=target, **limits)
    except (errors.SolveError, errors.CertificateError) as failure:
        record.update(outcome=type(failure).__name__, message=str(failure),
                      status=failure.result.status, iterations=failure.result.iterations,
                      certificate_valid=bool(failure.result.certificate.valid),
                      seconds=round(time.perf_counter() - start, 3))
        _log(record)
        assert "\n" not in str(failure) and failure.exit_status == 1
        assert failure.result is not None and not failure.result.success
        if isinstance(failure, errors.SolveError):
            assert failure.result.status in str(failure) and not failure.result.solved
        return
    record.update(outcome="certified", status=result.status, iterations=result.iterations,
                  seconds=round(time.perf_counter() - start, 3))
    _log(record)
    assert result.success and result.certificate.valid
    assert result.certificate.flipped == 0 and abs(result.certificate.degree - 1) < 1e-9
    np.testing.assert_allclose(np.linalg.norm(result.vertices, axis=1), 1, atol=1e-9)
    # A valid random mesh needs no repair: same vertices, same faces, same order.
    assert result.repairs == []
    np.testing.assert_array_equal(result.vertex_map, np.arange(len(V)))
    np.testing.assert_array_equal(result.faces, F)


# Failures found by this test, kept as explicit examples (they are clean failures today, and must stay
# certified-or-clean when the solver changes):
# * IPOPT converges, but to angles with a zero excess: the inequality stage returns the same point.
# * IPOPT stops at Solved_To_Acceptable_Level with 3 flipped triangles, which the certificate catches.
# * IPOPT's Solve_Succeeded with all constraints met (violation 4e-12) but one excess at 2e-13: the
#   unfolding cannot close (edge chords mismatch by 0.9) and the certificate finds 6 flipped triangles.
#   (The log-chord formulation solves this mesh.)
# * A margin stage that diverges with a corner past pi: the unfolding's sine-law chords took the
#   arcsin of -1.02 (RuntimeWarning, NaN chords) before the certificate could say no.
@example(mesh=(8, 7, 7, 0.1), target="original-angles")
@example(mesh=(18, 195197, 7, 0.0), target="equal-angles")
@example(mesh=(12, 12, 12, 0.1), target="original-angles")
@example(mesh=(8, 4758992, 8, 0.1), target="original-angles")
@example(mesh=(8, 1001, 8, 0.1), target="original-angles")
@settings(max_examples=50, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(mesh=random_meshes(), target=st.sampled_from(TARGETS))
def test_random_genus0_meshes_certified_or_clean_failure(mesh, target):
    check_certified_or_clean_failure(mesh, target, DEFAULT_LIMITS)


@pytest.mark.slow
@settings(max_examples=1000, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(mesh=random_meshes(), target=st.sampled_from(TARGETS))
def test_random_genus0_meshes_certified_or_clean_failure_1000(mesh, target):
    check_certified_or_clean_failure(mesh, target, SLOW_LIMITS)


@settings(max_examples=20, deadline=None)
@given(mesh=random_meshes())
def test_random_meshes_are_valid_genus0_surfaces(mesh):
    # The generator itself: closed, manifold, genus 0, consistently oriented, no degenerate face.
    from sphere_nlp.repair import prepare_mesh

    n_points, seed, n_flips, jitter = mesh
    V, F = meshgen.random_genus0_mesh(n_points, seed, n_flips=n_flips, jitter=jitter)
    prepared = prepare_mesh(V, F)
    assert prepared.repairs == [] and len(F) == 2 * len(V) - 4
