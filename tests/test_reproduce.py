"""``python -m sphere_nlp reproduce fig3``: outputs, certificates, and the paper's four findings."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import MODELS
from sphere_nlp.certify import certify, spherical_angles
from sphere_nlp.mesh_io import load_mesh
from sphere_nlp.reproduce import BLACK_TRIANGLE, SIDE_TRIANGLES
from sphere_nlp.shapes import cylinder

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def fig3(tmp_path_factory):
    """Run the command once; return (output folder, {panel: record}, wall-clock seconds)."""
    out = tmp_path_factory.mktemp("fig3")
    clock = time.perf_counter()
    p = subprocess.run([sys.executable, "-m", "sphere_nlp", "reproduce", "fig3", "--out", str(out)],
                       capture_output=True, text=True)
    seconds = time.perf_counter() - clock
    assert p.returncode == 0, p.stderr
    records = json.loads((out / "fig3.json").read_text())
    return out, {r["panel"]: r for r in records}, seconds


def test_fig3_writes_figure_meshes_and_numbers_in_under_a_minute(fig3):
    out, panels, seconds = fig3
    assert seconds < 60
    assert sorted(panels) == list("abcdef")
    png = (out / "fig3.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 50_000   # six shaded panels, not a blank
    from matplotlib.image import imread

    pixels = imread(out / "fig3.png")[..., :3].mean(axis=2)
    assert pixels.shape == (800, 1200)
    assert 0.2 < (pixels < 0.95).mean() < 0.8        # drawn surfaces and white background
    assert (pixels < 0.05).mean() > 0.005            # the black triangles and the edges
    keys = {"panel", "method", "target", "valid", "mean_abs_angle_diff_deg", "mean_abs_log_area",
            "area_cv", "min_angle_deg", "black_triangle_angles_deg", "cap_area_share", "time_s"}
    V, F = cylinder()
    for panel, record in panels.items():
        assert keys <= set(record)
        assert len(record["black_triangle_angles_deg"]) == 3
        X, faces = load_mesh(out / ("fig3_%s.off" % panel))
        np.testing.assert_array_equal(faces, F)
    # Panel (a) is the shipped model.
    shipped = load_mesh(MODELS / "cylinder.off")
    a = load_mesh(out / "fig3_a.off")
    np.testing.assert_array_equal(a[1], shipped[1])
    np.testing.assert_allclose(a[0], shipped[0], atol=1e-15)


def test_fig3_all_computed_panels_are_certified(fig3):
    out, panels, _ = fig3
    assert panels["a"]["valid"]                      # by convention
    F = cylinder()[1]
    for panel in "bcdef":
        assert panels[panel]["valid"], panel
        X, _ = load_mesh(out / ("fig3_%s.off" % panel))
        assert certify(X, F).valid, panel            # the file itself, not just the report
    assert panels["b"]["converged"]


def test_fig3_panel_a_describes_the_cylinder_itself(fig3):
    a = fig3[1]["a"]
    assert a["mean_abs_angle_diff_deg"] == 0 and a["mean_abs_log_area"] == 0
    assert sorted(a["black_triangle_angles_deg"])[2] == pytest.approx(90)


def test_finding_e_black_triangle_stays_right_angled(fig3):
    panels = fig3[1]
    e = np.array(panels["e"]["black_triangle_angles_deg"])
    cylinder_angles = np.array(panels["a"]["black_triangle_angles_deg"])       # 32.8, 90, 57.2
    assert min(abs(e - 90)) < 10                                                 # measured 89.9
    # The right angle stays at the same corner, and the whole shape is kept (measured within 5.7
    # degrees); the other maps reshape it (equal areas: 44, 62, 77 degrees).
    assert np.argmin(abs(e - 90)) == np.argmin(abs(cylinder_angles - 90))
    assert np.abs(e - cylinder_angles).max() < 8
    # Aiming for equal angles makes it near-equilateral instead.
    assert min(abs(a - 90) for a in panels["c"]["black_triangle_angles_deg"]) > 20


def test_finding_d_equal_areas_evens_areas_at_the_cost_of_skinny_triangles(fig3):
    c, d = fig3[1]["c"], fig3[1]["d"]
    assert d["area_cv"] < c["area_cv"] / 3                       # measured 0.047 vs 0.348
    # The smallest corner over all triangles is 30 degrees in both maps: the 12 triangles of each cap
    # fan meet at the cap centre and share its 360 degrees evenly (the maps are symmetric). The
    # skinny triangles the paper sees appear on the side, so compare the side triangles' smallest
    # corner (measured 25.3 vs 48.6 degrees) and require (d) no better overall.
    assert d["min_side_angle_deg"] < c["min_side_angle_deg"] - 5
    assert d["min_angle_deg"] <= c["min_angle_deg"] + 1e-6


def test_finding_f_cap_triangles_get_much_larger_areas(fig3):
    panels = fig3[1]
    assert panels["f"]["cap_area_share"] > 2 * panels["c"]["cap_area_share"]   # 0.33 vs 0.12
    # The 24 cap triangles are 14% of all triangles; in (f) they cover a third of the sphere.
    assert panels["f"]["cap_area_share"] > 0.3


def test_finding_b_alexa_looks_like_c_equal_angles(fig3):
    out, panels, _ = fig3
    b, c = panels["b"], panels["c"]
    # Across the five sphere panels mean_abs_angle_diff_deg spans 4 to 21 degrees; (b) and (c)
    # measured 18.9 vs 18.8. A 1-degree tolerance is 7 times that gap yet below the gap from (c) to
    # any other panel (2.6 degrees to (d), 12-15 to (e), (f)), so it asserts "(b) is like (c)" and
    # not "(b) is like everything". area_cv (0.33 vs 0.35) is a looser check: (e) has 0.34 too.
    assert abs(b["mean_abs_angle_diff_deg"] - c["mean_abs_angle_diff_deg"]) < 1
    assert abs(b["area_cv"] - c["area_cv"]) < 0.05
    np.testing.assert_allclose(b["black_triangle_angles_deg"], c["black_triangle_angles_deg"], atol=3)
    # Corner by corner: (b)'s spherical angles differ from (c)'s by 2.8 degrees on average
    # (measured), against 8.9 degrees for the next most similar panel, (d).
    F = cylinder()[1]
    angles = {p: np.degrees(spherical_angles(load_mesh(out / ("fig3_%s.off" % p))[0], F)) for p in "bcdef"}
    gap = {p: np.abs(angles[p] - angles["c"]).mean() for p in "bdef"}
    assert gap["b"] < 4
    assert gap["b"] < 0.5 * min(gap[p] for p in "def")


def test_black_triangle_is_a_side_triangle_in_the_middle():
    V, F = cylinder()
    assert BLACK_TRIANGLE < SIDE_TRIANGLES
    z = V[F[BLACK_TRIANGLE], 2]
    assert z.min() >= 0 and z.max() <= 1 / 3 + 1e-12


def test_reproduce_unknown_figure_is_usage_error(tmp_path):
    p = subprocess.run([sys.executable, "-m", "sphere_nlp", "reproduce", "fig9", "--out", str(tmp_path)],
                       capture_output=True, text=True)
    assert p.returncode == 2 and "invalid choice" in p.stderr
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_an_interrupted_reproduce_writes_nothing(signum, tmp_path):
    # Panels (a)-(c) are done when (c)'s line comes: their files are staged, none in place yet.
    out = tmp_path / "r" / "fig"
    process = subprocess.Popen([sys.executable, "-m", "sphere_nlp", "reproduce", "fig3", "--out", str(out)],
                               stderr=subprocess.PIPE, text=True, cwd=ROOT)
    for line in process.stderr:
        if "(c) equal angles" in line:
            break
    process.send_signal(signum)
    rest = process.stderr.read()
    assert process.wait(timeout=60) == 128 + signum, rest
    assert rest.strip().splitlines()[-1] == "sphere-nlp reproduce: interrupted; nothing written (%s)" % (
        signal.Signals(signum).name)
    assert os.listdir(tmp_path) == []                      # not even the folders it made
