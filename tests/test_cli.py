"""Command line: outputs, report and solution files, exit statuses."""

import json
import subprocess
import sys

import numpy as np

from conftest import MODELS
from sphere_nlp.certify import certify, spherical_angles
from sphere_nlp.mesh_io import load_mesh


def run(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "sphere_nlp", *map(str, args)], capture_output=True,
                          text=True, cwd=cwd)


def test_cli_writes_certified_sphere_report_and_solution(tmp_path):
    out = tmp_path / "cyl.obj"
    p = run(MODELS / "cylinder.off", "-o", out, "--report", tmp_path / "r.json",
            "--save-solution", tmp_path / "s.npz", "--target", "equal-areas")
    assert p.returncode == 0, p.stderr
    X, F = load_mesh(out)
    V, F0 = load_mesh(MODELS / "cylinder.off")
    np.testing.assert_array_equal(F, F0)                   # same faces, same vertex order
    assert certify(X, F).valid
    report = json.loads((tmp_path / "r.json").read_text())
    for key in ("vertices", "faces", "target", "status", "iterations", "objective",
                "max_constraint_violation", "certificate", "timings_s", "peak_rss_mb"):
        assert key in report
    assert report["certificate"]["valid"] and report["max_constraint_violation"] <= 1e-8
    assert set(report["timings_s"]) >= {"load", "build", "solve", "unfold", "certify", "total"}
    sol = np.load(tmp_path / "s.npz")
    np.testing.assert_allclose(sol["vertices"], X, atol=0)
    assert np.abs(spherical_angles(X, F) - sol["angles"]).max() < 1e-6
    assert sol["target_angles"].shape == sol["angles"].shape == (len(F), 3)


def test_cli_default_output_name(tmp_path):
    p = run(MODELS / "cylinder.off", "--quiet", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert (tmp_path / "cylinder.sphere.off").is_file()
    assert p.stderr == ""


def test_cli_missing_file_is_exit_2(tmp_path):
    p = run(tmp_path / "nope.off", cwd=tmp_path)
    assert p.returncode == 2
    assert "no such file" in p.stderr and "Traceback" not in p.stderr
    assert list(tmp_path.iterdir()) == []


def test_cli_bad_usage_is_exit_2(tmp_path):
    p = run(MODELS / "cylinder.off", "--target", "nonsense", cwd=tmp_path)
    assert p.returncode == 2
    p = run(MODELS / "cylinder.off", "-o", tmp_path / "x.stl", cwd=tmp_path)
    assert p.returncode == 2 and "output must end in" in p.stderr
