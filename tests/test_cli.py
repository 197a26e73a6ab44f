"""Command line: outputs, report and solution files, exit statuses."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import MODELS
from sphere_nlp.certify import certify, spherical_angles
from sphere_nlp.mesh_io import load_mesh


ROOT = Path(__file__).resolve().parents[1]


def run(*args, cwd=None):
    # This checkout's sphere_nlp, from any working folder (the package need not be installed).
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    return subprocess.run([sys.executable, "-m", "sphere_nlp", *map(str, args)], capture_output=True,
                          text=True, cwd=cwd, env=env)


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


def test_compare_writes_rows_whose_metrics_match_recomputation(tmp_path):
    from sphere_nlp import parameterize
    from sphere_nlp.baselines import conformal_map, tutte_projection
    from sphere_nlp.metrics import distortion_summary

    methods = ["sphere_nlp:original-angles", "conformal", "tutte-projection"]
    p = run("compare", MODELS / "cylinder.off", "--out", tmp_path / "cmp", "--methods", ",".join(methods))
    assert p.returncode == 0, p.stderr
    assert "cylinder.off: tutte-projection: valid" in p.stderr          # progress lines on stderr
    rows = json.loads((tmp_path / "cmp" / "compare.json").read_text())
    assert [r["method"] for r in rows] == methods and {r["mesh"] for r in rows} == {"cylinder.off"}
    for row in rows:
        assert {"mesh", "method", "valid", "flipped", "mean_abs_angle_diff_deg", "qc_mean", "qc_max",
                "mean_abs_log_area", "time_s", "status", "note"} <= set(row)
        assert row["time_s"] >= 0
    by_method = {r["method"]: r for r in rows}
    assert by_method["sphere_nlp:original-angles"]["valid"] and by_method["tutte-projection"]["valid"]
    V, F = load_mesh(MODELS / "cylinder.off")
    recomputed = {"sphere_nlp:original-angles": parameterize((V, F), target="original-angles").vertices,
                  "conformal": conformal_map(V, F), "tutte-projection": tutte_projection(V, F)}
    for method, positions in recomputed.items():
        expected = distortion_summary(V, positions, F)
        for key, value in expected.items():
            assert by_method[method][key] == (value if not isinstance(value, float) else
                                              pytest.approx(value, rel=1e-9, abs=1e-12)), (method, key)
    table = (tmp_path / "cmp" / "compare.md").read_text().splitlines()
    assert table[0].startswith("| mesh | method | valid") and len(table) == 2 + len(methods)
    assert all(line.count("|") == table[0].count("|") for line in table)


def test_compare_records_a_failed_solve_as_a_row(tmp_path):
    p = run("compare", MODELS / "cylinder.off", "--out", tmp_path, "--methods", "sphere_nlp:equal-angles",
            "--max-time", "1e-6", "--quiet")
    assert p.returncode == 0 and p.stderr == ""
    (row,) = json.loads((tmp_path / "compare.json").read_text())
    assert row["valid"] is False and "failed" in row["status"]


def test_compare_checks_every_mesh_and_method_before_running_any(tmp_path):
    out = tmp_path / "cmp"
    p = run("compare", MODELS / "cylinder.off", "--out", out, "--methods", "conformal,nonsense")
    assert p.returncode == 2 and "unknown method 'nonsense'" in p.stderr and not out.exists()
    # A bad mesh after a good one: refused before the good one is solved (no progress line, no
    # row, no folder), so exit 2 means that nothing ran.
    garbage = tmp_path / "garbage.off"
    garbage.write_text("OFF\n4 4 0\n0 0 0\n")
    p = run("compare", MODELS / "cylinder.off", garbage, MODELS / "cylinder.off", "--out", out,
            "--methods", "sphere_nlp:original-angles")
    assert p.returncode == 2
    assert p.stderr.splitlines() == ["sphere-nlp compare: error: cannot read %s: truncated (header promises 4 "
                                     "vertices and 4 faces, found 1 and 0)" % garbage]
    assert not out.exists()
    p = run("compare", garbage, tmp_path / "missing.off", "--out", out)
    assert p.returncode == 2 and "(and 1 more mesh(es) rejected)" in p.stderr and not out.exists()
    # Nothing to run at all: the error, exit 2, nothing written.
    p = run("compare", tmp_path / "missing.off", "--out", tmp_path / "none")
    assert p.returncode == 2 and "missing.off" in p.stderr and not (tmp_path / "none").exists()


def test_compare_from_python_gives_a_rejected_mesh_a_row_and_runs_the_others(tmp_path):
    from sphere_nlp.compare import compare

    garbage = tmp_path / "garbage.off"
    garbage.write_text("OFF\n4 4 0\n0 0 0\n")
    rows = compare([garbage, MODELS / "cylinder.off"], tmp_path / "cmp", methods=["conformal"])
    assert [(r["mesh"], r["method"], r["valid"]) for r in rows] == [("garbage.off", "-", False),
                                                                   ("cylinder.off", "conformal", True)]
    assert rows[0]["status"].startswith("rejected: ") and "truncated" in rows[0]["status"]


def test_compare_defaults_to_a_few_fast_methods_and_saves_certified_maps(tmp_path):
    from sphere_nlp.certify import certify
    from sphere_nlp.compare import DEFAULT_METHODS

    p = run("compare", MODELS / "cylinder.off", "--out", tmp_path, "--save-maps", "-q")
    assert p.returncode == 0, p.stderr
    rows = json.loads((tmp_path / "compare.json").read_text())
    assert [r["method"] for r in rows] == list(DEFAULT_METHODS) and len(DEFAULT_METHODS) <= 4
    for row in rows:
        stem = "cylinder.%s" % row["method"].replace(":", "-")
        assert row["valid"] and row["files"] == [str(tmp_path / (stem + ".obj")), str(tmp_path / (stem + ".png"))]
        V, F = load_mesh(tmp_path / (stem + ".obj"))
        assert certify(V, F).valid
        assert (tmp_path / (stem + ".png")).read_bytes()[:4] == b"\x89PNG"


def test_compare_all_merge_from_replaces_and_adds_rows_without_solving(tmp_path):
    from pathlib import Path
    script = Path(__file__).resolve().parent.parent / "benchmarks" / "compare_all.py"
    docs = tmp_path / "docs"
    docs.mkdir()
    row = json.loads('{"mesh": "knight.off", "method": "conformal", "n_vertices": 502, "valid": true, '
                     '"flipped": 0, "mean_abs_angle_diff_deg": 1.0, "qc_mean": 1.1, "qc_max": 2.0, '
                     '"mean_abs_log_area": 0.5, "time_s": 0.1, "status": "valid"}')
    old = [row, dict(row, method="cmcf")]
    (docs / "compare.json").write_text(json.dumps(old))
    new = [dict(row, method="cmcf", qc_mean=9.5), dict(row, mesh="spot.obj")]
    (tmp_path / "new.json").write_text(json.dumps(new))
    proc = subprocess.run([sys.executable, str(script), "--merge-from", str(tmp_path / "new.json"),
                           "--out", str(docs)], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    rows = json.loads((docs / "compare.json").read_text())
    assert sorted((r["mesh"], r["method"], r["qc_mean"]) for r in rows) == [
        ("knight.off", "cmcf", 9.5), ("knight.off", "conformal", 1.1), ("spot.obj", "conformal", 1.1)]
    table = (docs / "compare.md").read_text()
    assert "9.5" in table and "spot.obj" in table
    assert sorted(p.name for p in docs.iterdir()) == ["compare.json", "compare.md"]


def test_finish_trace_certifies_a_trace_end_point_as_compare_would(tmp_path):
    # The big area-mode rows of docs/compare.md come from traces of the NLP: their rows must be what
    # `compare` gives for the same solve (the same NLP, in an angle mode), and the sphere they write
    # must certify.
    from pathlib import Path
    benchmarks = Path(__file__).resolve().parent.parent / "benchmarks"
    trace = tmp_path / "trace"
    with open(tmp_path / "trace.txt", "w") as log:
        proc = subprocess.run([sys.executable, str(benchmarks / "trace_solve.py"), str(MODELS / "cylinder.off"),
                               "original-angles", "--out", str(trace)], stdout=log, stderr=subprocess.PIPE,
                              text=True)
    assert proc.returncode == 0, proc.stderr
    sphere = tmp_path / "cylinder.sphere.off"
    proc = subprocess.run([sys.executable, str(benchmarks / "finish_trace.py"), str(MODELS / "cylinder.off"),
                           "original-angles", str(trace), "--log", str(tmp_path / "trace.txt"),
                           "--row", str(tmp_path / "row.json"), "--sphere", str(sphere)],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    [row] = json.loads((tmp_path / "row.json").read_text())
    assert run("compare", MODELS / "cylinder.off", "--out", tmp_path / "cmp",
               "--methods", "sphere_nlp:original-angles").returncode == 0
    [reference] = json.loads((tmp_path / "cmp" / "compare.json").read_text())
    assert row["valid"] and row["status"] == "certified"
    for key in ("n_vertices", "flipped", "mean_abs_angle_diff_deg", "qc_mean", "qc_max", "mean_abs_log_area"):
        assert row[key] == pytest.approx(reference[key], rel=1e-9), key
    V, F = load_mesh(sphere)
    assert certify(V, F).valid


@pytest.mark.parametrize("argv", [["compare", "x.off"], ["reproduce", "fig9"], ["resample", "x.off"],
                                  ["morph", "a.off"], ["transfer", "a.off", "b.off"]])
def test_subcommand_usage_errors_are_one_line_with_exit_2(argv, capsys):
    from sphere_nlp.cli import main

    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("sphere-nlp %s: error: " % argv[0]), err


def test_cli_starts_from_an_earlier_sphere_and_solves_it_again_in_a_few_iterations(tmp_path):
    # --start reads a sphere written for the mesh; a map solved again from itself skips the area
    # modes' walk (it is at its targets already) and ends at the same optimum.
    first, again = tmp_path / "first.off", tmp_path / "again.off"
    p = run(MODELS / "cylinder.off", "-o", first, "--target", "original-areas", "--start", "conformal",
            "--report", tmp_path / "1.json")
    assert p.returncode == 0, p.stderr
    p = run(MODELS / "cylinder.off", "-o", again, "--target", "original-areas", "--start", first,
            "--report", tmp_path / "2.json")
    assert p.returncode == 0, p.stderr
    report1, report2 = (json.loads((tmp_path / name).read_text()) for name in ("1.json", "2.json"))
    assert [s["name"] for s in report2["stages"]] == ["margin"]
    assert report2["iterations"] <= 10 < report1["iterations"]
    assert report2["objective"] <= report1["objective"] * (1 + 1e-6) and report2["certificate"]["valid"]
    X, F = load_mesh(again)
    assert certify(X, F).valid


@pytest.mark.parametrize("start, fragment", [("missing.off", "--start: cannot read"),
                                             ("other.off", "the start has 8 positions, the mesh"),
                                             ("flat.off", "start positions are not a valid spherical map")])
def test_cli_refuses_a_start_that_is_not_a_sphere_of_the_mesh(start, fragment, tmp_path, capsys):
    from sphere_nlp.cli import main
    from sphere_nlp.mesh_io import write_mesh
    from sphere_nlp.shapes import octahedron

    V, F = load_mesh(MODELS / "cylinder.off")
    write_mesh(tmp_path / "flat.off", V, F)                  # the mesh itself: not on the sphere
    octa_V, octa_F = octahedron()
    write_mesh(tmp_path / "other.off", np.vstack([octa_V, octa_V[:2] * 0.5]), octa_F)
    out = tmp_path / "out.off"
    assert main([str(MODELS / "cylinder.off"), "-o", str(out), "--start", str(tmp_path / start)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("sphere-nlp: error: ") and fragment in err[0], err
    assert not out.exists()
