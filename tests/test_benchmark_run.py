"""benchmarks/run.py: the rows it records for finished, hierarchical and capped cases;
benchmarks/anytime.py: its trace of a solve's iterates."""

import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import MODELS

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
import run as bench  # noqa: E402  (the benchmark script, imported as a module)

CYLINDER = str(MODELS / "cylinder.off")


def test_finished_case_row_is_certified_and_progress_is_reported(capsys):
    # A line per report interval while the case runs; the row is the worker's own report.
    row = bench.run_case(CYLINDER, "equal-angles", "log-chord", cap_s=120, report_every_s=0.2)
    assert row["status"] == "Solve_Succeeded"
    assert row["certificate"]["valid"] and row["certificate"]["flipped"] == 0
    assert row["max_constraint_violation"] < 1e-8
    assert row["iterations"] == sum(stage["iterations"] for stage in row["stages"]) > 0
    lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("  ... ")]
    assert all(" iteration " in line and "objective" in line for line in lines)


def test_loop_from_coarse_row_counts_the_coarse_solve():
    row = bench.run_case("loop-from-coarse:" + CYLINDER, "equal-areas", "log-chord", cap_s=120)
    assert row["certificate"]["valid"] and row["max_constraint_violation"] < 1e-8
    assert row["vertices"] > row["coarse"]["vertices"] == 86          # 1-to-4 subdivision of the cylinder
    assert row["timings_s"]["total"] >= row["timings_s"]["fine_total"] + row["coarse"]["total_s"] * 0.99
    assert bench.iterations_text(row) == "%d + %d" % (row["coarse"]["iterations"], row["iterations"])


def test_capped_case_is_recorded_as_capped():
    row = bench.run_case(CYLINDER, "original-areas", "log-chord", cap_s=0.01)
    assert row["status"].startswith("cap ") and "certificate" not in row
    assert row["wall_s"] < 30


def test_capped_hierarchy_row_says_where_each_level_was():
    row = {"status": "cap 9000 s hit",
           "progress": {"stages": [["coarse area-continuation", 30], ["coarse margin", 700],
                                   ["area-continuation", 30], ["margin", 12]],
                        "objective": 2.5, "violation": 1e-3, "elapsed_s": 9000.0}}
    assert bench.iterations_text(row) == ">= 730 + 42"
    assert bench.status_text(row) == "cap 9000 s hit (in margin at iteration 12: objective 2.5, violation 1.0e-03)"
    plain = {"status": "cap 5 s hit", "progress": {"stages": [["margin", 7]], "objective": 1.0,
                                                   "violation": 0.0, "elapsed_s": 5.0}}
    assert bench.iterations_text(plain) == ">= 7"
    assert bench.progress_text(plain["progress"], 90.0) == "1.5 min: margin iteration 7, objective 1, violation 0.0e+00"


@pytest.mark.parametrize("mesh, label", [("/x/armadillo.obj", "armadillo.obj"), ("ellipsoid:4", "ellipsoid:4"),
                                         ("limbs:22k", "limbs:22k"),
                                         ("loop:/x/armadillo.obj", "loop:armadillo.obj"),
                                         ("loop-from-coarse:/x/armadillo.obj",
                                          "loop:armadillo.obj from its parent's solution")])
def test_mesh_labels(mesh, label):
    assert bench.mesh_label(mesh) == label


def test_time_limit_and_on_limit_reach_the_worker_and_the_row():
    # Passed to parameterize (a limit this run does not reach: an ordinary, converged row).
    row = bench.run_case("loop-from-coarse:" + CYLINDER, "original-areas", "log-chord", cap_s=120,
                         max_time=60.0, on_limit="project")
    assert row["max_time_s"] == 60.0 and row["on_limit"] == "project"
    assert row["converged"] and row["coarse"]["converged"] and row["certificate"]["valid"]
    assert bench.status_text(row) == "Solve_Succeeded"


def test_projected_rows_say_they_are_not_optimal():
    row = {"status": "Maximum_WallTime_Exceeded", "success": True, "converged": False, "max_time_s": 1200.0,
           "coarse": {"converged": False}}
    assert bench.status_text(row) == ("Maximum_WallTime_Exceeded (coarse and fine stopped at the 1200-s "
                                      "stage limit and projected: not optimal)")
    row = {"status": "Solve_Succeeded", "success": True, "converged": True, "max_time_s": 1200.0,
           "coarse": {"converged": False}}
    assert "coarse stopped" in bench.status_text(row)


def test_a_rerun_replaces_its_row_and_keeps_what_it_said_beside_it(tmp_path):
    def row(mesh, iterations, total, objective, commit, valid=True):
        return {"mesh": mesh, "mode": "equal-angles", "formulation": "log-chord", "iterations": iterations,
                "timings_s": {"total": total}, "objective": objective, "certificate": {"valid": valid},
                "commit": commit}

    rows = [row("a.off", 88, 1.7, 330.709, "old1"), row("b.off", 12, 0.5, 1.0, "old2")]
    rows = bench.replace_row(rows, row("a.off", 12, 0.5, 330.709, "new"))
    assert [r["mesh"] for r in rows] == ["b.off", "a.off"] and "previous" not in rows[0]
    assert bench.previous_text(rows[1]) == "88 its, 1.7 s, 330.709 (old1)"
    rows[1]["certificate"]["valid"] = False                              # an uncertified row says so
    rows = bench.replace_row(rows, row("a.off", 11, 0.4, 330.709, "newer"))
    assert bench.previous_text(rows[-1]) == "12 its, 0.5 s, not certified (new)"
    bench.write_tables(rows, str(tmp_path / "t.md"))
    table = (tmp_path / "t.md").read_text()
    assert "| previous row |" in table and "12 its, 0.5 s, not certified (new) |" in table


def test_anytime_trace_ends_at_the_certified_optimum_and_its_row_reads_each_fraction():
    import anytime

    result, total, rows = anytime.trace(CYLINDER, "original-areas", every=5)
    assert result.success
    assert [row["seconds"] for row in rows] == sorted(row["seconds"] for row in rows) and rows[-1]["seconds"] <= total
    # The last kept point is the last run's end, evaluated by the last stage's NLP: the result itself.
    assert rows[-1]["objective"] == pytest.approx(result.objective, rel=1e-9)
    assert rows[-1]["violation"] < 1e-8
    assert rows[-1]["mean_abs_log_area"] == pytest.approx(
        np.abs(np.log(result.excess / result.target_excess)).mean(), abs=1e-9)
    assert {row["stage"] for row in rows} >= {"area-continuation-1", "margin"}
    cells = anytime.markdown_row(CYLINDER, "original-areas", result, total, rows).split(" | ")
    assert len(cells) == 10 and cells[0] == "| cylinder.off" and cells[-1].endswith(" |")
    at_three_quarters = [r for r in rows if r["seconds"] <= 0.75 * total][-1]
    assert cells[-1].split(" / ")[1].rstrip(" |") == "%.3f" % at_three_quarters["mean_abs_log_area"]


def test_the_tables_note_survives_a_rewrite_and_a_file_without_one_has_none(tmp_path):
    # --append without --note keeps the note above the table (run.existing_note).
    rows = [{"mesh": "a.off", "mode": "equal-angles", "formulation": "log-chord", "iterations": 3,
             "timings_s": {"total": 1.0}, "objective": 1.0, "certificate": {"valid": True}, "commit": "c"}]
    path = tmp_path / "t.md"
    assert bench.existing_note(str(path)) == ""
    bench.write_tables(rows, str(path))
    assert bench.existing_note(str(path)) == ""
    bench.write_tables(rows, str(path), "Every row ran alone.")
    assert bench.existing_note(str(path)) == "Every row ran alone."
    bench.write_tables(rows, str(path), bench.existing_note(str(path)))
    assert path.read_text().count("Every row ran alone.") == 1


def test_hand_written_notes_below_the_table_survive_a_rewrite(tmp_path):
    # --append keeps what is written below run.POSTSCRIPT_MARK (runs outside the table).
    rows = [{"mesh": "a.off", "mode": "equal-angles", "formulation": "log-chord", "iterations": 3,
             "timings_s": {"total": 1.0}, "objective": 1.0, "certificate": {"valid": True}, "commit": "c"}]
    path = tmp_path / "t.md"
    bench.write_tables(rows, str(path))
    assert bench.existing_postscript(str(path)) == ""
    postscript = "A 692k run.\n\nIts spread."
    bench.write_tables(rows, str(path), "", postscript)
    bench.write_tables(rows, str(path), "", bench.existing_postscript(str(path)))
    assert bench.existing_postscript(str(path)) == postscript
    assert path.read_text().count("A 692k run.") == 1
