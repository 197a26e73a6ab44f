"""Failures never damage files: atomic writes, solver limits, Ctrl-C while writing."""

import json
import os
import re

import pytest

import sphere_nlp
from sphere_nlp import mesh_io
from sphere_nlp.cli import main
from sphere_nlp.mesh_io import atomic_output, write_mesh

import meshgen

PRECIOUS = "an existing file that a failed run must not touch\n"


def run_cli(capsys, *args):
    status = main([str(a) for a in args])
    return status, capsys.readouterr().err


@pytest.fixture
def ellipsoid_file(tmp_path):
    """The stretched icosphere(2) (162 vertices): original-angles needs a few IPOPT iterations on it."""
    path = tmp_path / "ellipsoid.off"
    write_mesh(path, *meshgen.ellipsoid(2))
    return path


def leftovers(directory):
    """Temporary files the atomic writer might have left behind."""
    return [p.name for p in directory.iterdir() if p.name.endswith(".tmp")]


def test_max_iter_is_a_failure_with_ipopt_status_and_no_output(tmp_path, capsys, ellipsoid_file):
    out = tmp_path / "sphere.off"
    report = tmp_path / "report.json"
    status, stderr = run_cli(capsys, ellipsoid_file, "-o", out, "--max-iter", "1", "-q", "--report", report)
    assert status == 1
    lines = stderr.strip().splitlines()
    # The line says what the count counts (every stage has its own --max-iter) and what was written.
    assert len(lines) == 1 and re.fullmatch(r"sphere-nlp: error: the angle solve failed \(IPOPT status "
                                            r"Maximum_Iterations_Exceeded in stage [\w-]+ after 1 iteration; "
                                            r"(\d+) iterations over (\d+) stages in all, --max-iter limits "
                                            r"each stage\); nothing written but the report %s" % re.escape(str(report)),
                                            lines[0]), stderr
    total, stages = map(int, re.search(r"(\d+) iterations over (\d+) stages", lines[0]).groups())
    assert not out.exists() and leftovers(tmp_path) == []
    # The report is still written, complete, and says why: it documents the failure.
    written = json.loads(report.read_text())
    assert written["success"] is False and written["status"] == "Maximum_Iterations_Exceeded"
    assert written["iterations"] == total and len(written["stages"]) == stages
    assert all(stage["iterations"] <= 1 for stage in written["stages"])


def test_max_time_is_a_failure_with_ipopt_status(tmp_path, capsys, ellipsoid_file):
    out = tmp_path / "sphere.off"
    status, stderr = run_cli(capsys, ellipsoid_file, "-o", out, "--max-time", "1e-6", "-q")
    assert status == 1 and "Maximum_WallTime_Exceeded" in stderr
    assert not out.exists()


def test_api_solver_limit_raises_solve_error_with_the_partial_result(tmp_path):
    with pytest.raises(sphere_nlp.SolveError, match="Maximum_Iterations_Exceeded") as info:
        sphere_nlp.parameterize(meshgen.ellipsoid(2), max_iter=1)
    assert info.value.exit_status == 1
    assert info.value.result is not None and not info.value.result.success
    result = info.value.result
    # (Started from a valid embedding, the stopped iterate may well unfold to a valid sphere; it is
    # still not the solution, so it is a failure.)
    assert result.status == "Maximum_Iterations_Exceeded"
    # The result of a stopped solve refuses to be written.
    with pytest.raises(sphere_nlp.SolveError, match="refusing to write"):
        result.write(tmp_path / "s.off")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("failure", ["bad-input", "solver-limit"])
def test_existing_output_is_untouched_when_the_run_fails(failure, tmp_path, capsys, ellipsoid_file):
    out = tmp_path / "sphere.obj"
    out.write_text(PRECIOUS)
    if failure == "bad-input":
        source = tmp_path / "torus.off"
        write_mesh(source, *meshgen.torus())
        status, _ = run_cli(capsys, source, "-o", out, "-q")
        assert status == 2
    else:
        status, _ = run_cli(capsys, ellipsoid_file, "-o", out, "--max-iter", "1", "-q")
        assert status == 1
    assert out.read_text() == PRECIOUS
    assert leftovers(tmp_path) == []


def test_existing_output_is_replaced_by_a_certified_result(tmp_path, capsys, ellipsoid_file):
    out = tmp_path / "sphere.obj"
    out.write_text(PRECIOUS)
    status, _ = run_cli(capsys, ellipsoid_file, "-o", out, "-q")
    assert status == 0 and out.read_text() != PRECIOUS and leftovers(tmp_path) == []


class _InterruptedFile:
    """A file object whose second write raises KeyboardInterrupt, as Ctrl-C in mid-write would."""

    def __init__(self, handle):
        self.handle = handle
        self.writes = 0

    def write(self, text):
        self.writes += 1
        if self.writes == 2:
            raise KeyboardInterrupt
        return self.handle.write(text)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.handle.close()
        return False


@pytest.mark.parametrize("existing", [False, True])
def test_ctrl_c_while_writing_leaves_nothing(existing, tmp_path, capsys, monkeypatch, ellipsoid_file):
    out = tmp_path / "sphere.off"
    if existing:
        out.write_text(PRECIOUS)
    real_fdopen = os.fdopen
    monkeypatch.setattr(mesh_io.os, "fdopen", lambda fd, mode="r": _InterruptedFile(real_fdopen(fd, mode)))
    status, stderr = run_cli(capsys, ellipsoid_file, "-o", out, "-q")
    assert status == 130 and "interrupted; nothing written" in stderr
    assert (out.read_text() == PRECIOUS) if existing else not out.exists()
    assert leftovers(tmp_path) == []


def test_ctrl_c_during_the_solve_leaves_the_existing_output(tmp_path, capsys, monkeypatch, ellipsoid_file):
    import sphere_nlp.api

    out = tmp_path / "sphere.off"
    out.write_text(PRECIOUS)

    def interrupted_solve(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(sphere_nlp.api, "solve_angles", interrupted_solve)
    status, stderr = run_cli(capsys, ellipsoid_file, "-o", out, "-q")
    assert status == 130 and stderr.strip() == "sphere-nlp: interrupted; nothing written (SIGINT)"
    assert out.read_text() == PRECIOUS and leftovers(tmp_path) == []


def test_ctrl_c_just_before_the_rename_leaves_nothing(tmp_path, capsys, monkeypatch, ellipsoid_file):
    out = tmp_path / "sphere.off"

    def interrupted_replace(source, target):
        raise KeyboardInterrupt

    monkeypatch.setattr(mesh_io.os, "replace", interrupted_replace)
    status, _ = run_cli(capsys, ellipsoid_file, "-o", out, "-q")
    assert status == 130 and not out.exists() and leftovers(tmp_path) == []


@pytest.mark.parametrize("error", [KeyboardInterrupt, RuntimeError, SystemExit])
def test_atomic_output_removes_its_temporary_file_on_any_exception(error, tmp_path):
    target = tmp_path / "x.json"
    target.write_text(PRECIOUS)
    with pytest.raises(error):
        with atomic_output(target) as handle:
            handle.write("partial")
            raise error()
    assert target.read_text() == PRECIOUS and sorted(p.name for p in tmp_path.iterdir()) == ["x.json"]
