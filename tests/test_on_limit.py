"""on_limit="project": a margin stage stopped by max_iter / max_time still ends in a certified sphere.

The area-mode cases run the NLP alone (start="conformal"), without the authalic route of
sphere_nlp.polish, whose polish always projects (tests/test_authalic.py)."""

import json

import numpy as np
import pytest

import sphere_nlp
from sphere_nlp.cli import main
from sphere_nlp.mesh_io import write_mesh
from sphere_nlp.solve import constraint_residuals

import meshgen


@pytest.fixture(scope="module")
def ellipsoid():
    return meshgen.ellipsoid(2)


@pytest.fixture(scope="module")
def converged(ellipsoid):
    return sphere_nlp.parameterize(ellipsoid, "original-areas", start="conformal")


@pytest.fixture(scope="module")
def stopped(ellipsoid):
    return sphere_nlp.parameterize(ellipsoid, "original-areas", max_iter=3, on_limit="project", start="conformal")


def test_stopped_margin_stage_is_projected_onto_the_constraints(stopped):
    assert stopped.success and stopped.solved and not stopped.converged
    assert stopped.status == "Maximum_Iterations_Exceeded"
    names = [s["name"] for s in stopped.stages]
    assert names[-2:] == ["margin", "projection"]
    assert stopped.stages[-2]["status"] == "Maximum_Iterations_Exceeded"
    assert stopped.stages[-1]["status"] == "Solve_Succeeded"
    # Feasible: every equality (6)-(8) and the inequalities hold, and the sphere certifies.
    residuals = constraint_residuals(stopped_connectivity(stopped), stopped.angles, stopped.excess)
    assert max(np.max(np.abs(r)) for r in residuals.values()) <= 1e-8
    assert stopped.angles.min() > 0 and stopped.excess.min() > 0
    assert stopped.certificate.valid and stopped.certificate.flipped == 0
    assert np.allclose(np.linalg.norm(stopped.vertices, axis=1), 1.0, atol=1e-12)


def stopped_connectivity(result):
    from sphere_nlp.connectivity import build_connectivity
    return build_connectivity(result.faces, len(result.vertices))


def test_projection_is_near_the_optimum_not_at_it(stopped, converged):
    # Not optimal, but the projection keeps the stopped iterate's objective (within 10% of the
    # converged solve's here), and a converged run reports itself as such.
    assert converged.converged and converged.status == "Solve_Succeeded"
    assert not any(s["name"] == "projection" for s in converged.stages)
    assert stopped.objective == pytest.approx(converged.objective, rel=0.1)


def test_limit_not_reached_gives_the_same_result_either_way(ellipsoid, converged):
    projected = sphere_nlp.parameterize(ellipsoid, "original-areas", on_limit="project", start="conformal")
    assert projected.converged and projected.objective == converged.objective
    assert np.array_equal(projected.vertices, converged.vertices)


def test_default_still_fails_at_the_limit(ellipsoid):
    with pytest.raises(sphere_nlp.SolveError, match="Maximum_Iterations_Exceeded"):
        sphere_nlp.parameterize(ellipsoid, "original-areas", max_iter=3, start="conformal")


def test_cli_writes_the_projected_sphere_and_says_it_is_not_optimal(tmp_path, capsys, ellipsoid):
    source, out, report = tmp_path / "e.off", tmp_path / "e.sphere.off", tmp_path / "r.json"
    write_mesh(source, *ellipsoid)
    status = main([str(source), "-o", str(out), "--target", "original-areas", "--max-iter", "3",
                   "--on-limit", "project", "--start", "conformal", "--report", str(report)])
    lines = capsys.readouterr().err.strip().splitlines()
    assert status == 0 and out.exists()
    assert "NOT OPTIMAL" in lines[-1] and "Maximum_Iterations_Exceeded" in lines[-1]
    written = json.loads(report.read_text())
    assert written["success"] is True and written["converged"] is False


def test_projection_is_a_stage_with_the_same_time_limit(tmp_path, capsys, ellipsoid):
    # max_time applies to the projection too: with no time at all it cannot finish, so the run fails.
    source, out = tmp_path / "e.off", tmp_path / "e.sphere.off"
    write_mesh(source, *ellipsoid)
    status = main([str(source), "-o", str(out), "--max-time", "1e-6", "--on-limit", "project", "-q"])
    assert status == 1 and not out.exists()
    assert "Maximum_WallTime_Exceeded" in capsys.readouterr().err


def test_unknown_on_limit_is_a_usage_error(ellipsoid):
    with pytest.raises(sphere_nlp.UsageError, match="on_limit"):
        sphere_nlp.parameterize(ellipsoid, on_limit="continue")
