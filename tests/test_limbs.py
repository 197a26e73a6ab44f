"""Limbed bodies in the default mode, and runs whose numbers go bad: each ends cleanly.

The limbed bodies (tests/meshgen.py ``limbed_body``) stand for scanned animals: a conformal map
shrinks each limb exponentially in its length over its radius, far below the area floor.
"""

import os
import subprocess
import sys
import textwrap
import warnings
from pathlib import Path

import numpy as np
import pytest

from meshgen import COLLAPSING_LIMBS, FINGERED_BODY, LIMBED_BODIES, THIN_LIMBED_BODIES, ellipsoid, limbed_body
from sphere_nlp import parameterize
from sphere_nlp.certify import certify, signed_solid_angles
from sphere_nlp.connectivity import build_connectivity
from sphere_nlp.errors import SolveError
from sphere_nlp.settings import DEFAULT_SETTINGS

ROOT = Path(__file__).resolve().parents[1]


def test_the_limbed_body_is_closed_genus_zero_and_outward():
    V, F = limbed_body(n_limbs=4, subdivisions=3, radius=0.3, length_ratios=(10, 20))
    c = build_connectivity(F, len(V))
    assert len(V) - c.n_edges + len(F) == 2
    assert np.all(np.bincount(F.ravel(), minlength=len(V)) > 0)
    # Outward: the signed volume is positive, and each limb reaches out to its length.
    volume = np.einsum("ij,ij->i", V[F[:, 0]], np.cross(V[F[:, 1]], V[F[:, 2]])).sum() / 6
    assert volume > 0
    assert np.linalg.norm(V, axis=1).max() > 1 + 10 * 0.3
    # Claws: spikes of needle triangles at the first limbs' tips.
    from sphere_nlp.geometry import corner_angles
    assert np.degrees(corner_angles(V, F).min()) < 15


def test_a_conformal_start_whose_limb_tips_collapse_stays_finite_and_quiet(capfd):
    """The plane of FLASH's second step has tip triangles of zero area here (mu = 0/0 in the
    Beltrami form, and SuperLU then printed BLAS complaints): no RuntimeWarning, nothing on the
    terminal, a finite map and a certified start."""
    from sphere_nlp.conformal import conformal_map
    from sphere_nlp.starts import starting_positions
    V, F = limbed_body(**COLLAPSING_LIMBS)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        S = conformal_map(V, F)
        start, kind = starting_positions(build_connectivity(F, len(V)), V)
    assert np.isfinite(S).all() and np.allclose(np.linalg.norm(S, axis=1), 1)
    assert certify(start, F).valid and kind.startswith("conformal")
    out, err = capfd.readouterr()
    assert out == "" and err == ""


def test_every_sparse_solve_refuses_a_non_finite_system():
    import scipy.sparse as sp
    from sphere_nlp import sparse_lu
    from sphere_nlp.conformal import _dirichlet_solve, cotan_laplacian
    V, F = ellipsoid(1)
    K = cotan_laplacian(V, F).tolil()
    K[3, 4] = K[4, 3] = np.nan
    with pytest.raises(sparse_lu.NonFiniteSystem):
        _dirichlet_solve(K.tocsr(), np.zeros((len(V), 2)), [0, 1, 2])
    lu = sparse_lu.factorize(sp.identity(3, format="csc"))
    with pytest.raises(sparse_lu.NonFiniteSystem):
        lu.solve(np.array([1.0, np.inf, 0.0]))


def _nan_from_the_third_hessian(name, evaluator, x, lam_f, lam_g, values):
    _nan_from_the_third_hessian.calls += 1
    if _nan_from_the_third_hessian.calls >= 3:
        values = values.copy()
        values[::7] = np.nan
    return values


def test_a_nan_in_a_stage_ends_it_at_once_and_the_run_fails_cleanly():
    # Every Hessian from the third on has NaNs: each stage stops with IPOPT's
    # Invalid_Number_Detected at once, the fall-backs run and fail the same way, and the run
    # ends with one line (SolveError), not a hang.
    _nan_from_the_third_hessian.calls = 0
    settings = DEFAULT_SETTINGS.replace(modify_hessian=_nan_from_the_third_hessian)
    result = parameterize(ellipsoid(2), settings=settings, check=False)
    assert not result.success and result.status == "Invalid_Number_Detected"
    assert result.stages[0]["name"] == "margin" and result.stages[0]["iterations"] <= 3
    assert len(result.stages) > 1 and sum(s["iterations"] for s in result.stages) <= 10
    with pytest.raises(SolveError) as error:
        _nan_from_the_third_hessian.calls = 0
        parameterize(ellipsoid(2), settings=settings)
    assert "\n" not in str(error.value)


# In a process of its own: the BLAS under MUMPS (CasADi's OpenBLAS) refuses an illegal leading
# dimension once, in the third Hessian evaluation of the first stage, as it does when MUMPS hands
# it impossible dimensions; what it prints goes to the C standard output.
COMPLAINT_RUN = textwrap.dedent("""
    import ctypes, os, sys
    import numpy as np, casadi
    sys.path[:0] = [%(root)r, %(tests)r]
    from meshgen import ellipsoid
    from sphere_nlp import parameterize
    from sphere_nlp.settings import DEFAULT_SETTINGS
    blas = ctypes.CDLL(os.path.join(os.path.dirname(casadi.__file__), "libcasadi-tp-openblas.so"))
    calls = [0]
    def complain(name, evaluator, x, lam_f, lam_g, values):
        calls[0] += 1
        if calls[0] == 3:
            n, lda, inc = ctypes.c_int(4), ctypes.c_int(1), ctypes.c_int(1)
            A, v = np.eye(4), np.ones(4)
            blas.dtrsv_(b"L", b"N", b"U", ctypes.byref(n), A.ctypes.data_as(ctypes.c_void_p), ctypes.byref(lda),
                        v.ctypes.data_as(ctypes.c_void_p), ctypes.byref(inc))
        return values
    result = parameterize(ellipsoid(2), settings=DEFAULT_SETTINGS.replace(modify_hessian=complain), check=False)
    print("stages", [(s["name"], s["status"], s["iterations"]) for s in result.stages])
    print("success", result.success)
""")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="CasADi's bundled OpenBLAS by its Linux name")
def test_a_blas_complaint_under_ipopt_ends_the_stage_and_never_reaches_the_terminal():
    script = COMPLAINT_RUN % {"root": str(ROOT), "tests": str(ROOT / "tests")}
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert "illegal value" not in done.stdout + done.stderr
    lines = dict(line.split(" ", 1) for line in done.stdout.splitlines())
    stages = eval(lines["stages"])
    assert stages[0][:2] == ("margin", "Linear_Solver_Failed") and stages[0][2] <= 3
    # The fall-backs take over from there and the run certifies.
    assert len(stages) > 1 and lines["success"] == "True"


def test_a_map_that_shrinks_limbs_past_use_says_so_and_names_the_area_mode(tmp_path, capsys):
    from sphere_nlp.cli import main
    from sphere_nlp.mesh_io import write_mesh
    from sphere_nlp.metrics import SHRUNK_SHARE, area_log_ratio, normalised_areas_3d

    V, F = limbed_body(n_limbs=4, subdivisions=3, radius=0.3, length_ratios=(10, 20))
    mesh = tmp_path / "limbs.off"
    write_mesh(mesh, V, F)
    report = tmp_path / "r.json"
    assert main([str(mesh), "-o", str(tmp_path / "s.off"), "--report", str(report)]) == 0
    lines = [line for line in capsys.readouterr().err.splitlines() if "shrank parts of the surface" in line]
    assert len(lines) == 1 and "--target original-areas" in lines[0]
    import json
    shrinkage = json.loads(report.read_text())["shrinkage"]
    assert shrinkage["shrunk"] and shrinkage["note"] == lines[0]
    # The fraction it names is the limbs' share of the surface, measured here from the sphere written.
    from sphere_nlp.mesh_io import load_mesh
    S, _ = load_mesh(str(tmp_path / "s.off"))
    small = area_log_ratio(V, S, F) < np.log(SHRUNK_SHARE)
    share = normalised_areas_3d(V, F) / (4 * np.pi)
    assert shrinkage["shrunk_surface_fraction"] == pytest.approx(share[small].sum(), rel=1e-6)
    assert share[small].sum() > 0.1
    assert "%.3g%%" % (100 * share[small].sum()) in lines[0]
    # The area modes keep each triangle's share, so the line is the angle modes'; a round shape in
    # the default mode gets none.
    from sphere_nlp.metrics import shrinkage_summary
    assert shrinkage_summary(V, S, F, "original-areas")["note"] is None
    write_mesh(tmp_path / "e.off", *ellipsoid(2))
    assert main([str(tmp_path / "e.off"), "-o", str(tmp_path / "e.sphere.off")]) == 0
    assert "shrank parts" not in capsys.readouterr().err


def _certified_quickly(V, F):
    result = parameterize((V, F), "original-angles")
    assert result.success and result.certificate.valid and result.recovery is None
    assert result.usability()["corners_below_fraction"] == 0
    assert result.shrinkage()["shrunk"]
    return result


def test_a_small_limbed_body_certifies_in_the_default_mode():
    # 2,888 vertices, four limbs of 10-20 radii, two clawed: the start has triangles far below the
    # area floor, which keep their own size (max_floor_lift), so the solve takes tens of iterations.
    result = _certified_quickly(*limbed_body(n_limbs=4, subdivisions=3, radius=0.3, length_ratios=(10, 20)))
    assert result.iterations <= 60


# The limbed bodies of 20k-50k vertices (meshgen.LIMBED_BODIES; benchmarks/run.py --limbs): 4-8
# limbs of 10-30 radii, two to four clawed. With the start's tips lifted to the area floor the 27k
# one had not converged after 571 iterations and 900 s; tens of iterations now.
@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(LIMBED_BODIES))
def test_limbed_bodies_of_20k_to_50k_vertices_certify_in_the_default_mode(name):
    V, F = limbed_body(**LIMBED_BODIES[name])
    assert 20000 <= len(V) <= 50000
    result = _certified_quickly(V, F)
    assert result.iterations <= 80


# The eight-legged body (8 limbs of radius 0.1 and 20-45 radii, six clawed; 27.5k vertices): a
# fifth of its start's triangles are below double precision's reach, and the solve's path through
# them is chaotic (43-122 iterations on copies moved by 1e-10; docs/tuning.md, "The conformal start").
@pytest.mark.slow
@pytest.mark.parametrize("mode", ["original-angles", "equal-angles"])
def test_the_thin_eight_legged_body_certifies_in_the_angle_modes(mode):
    V, F = limbed_body(**THIN_LIMBED_BODIES["27k"])
    result = parameterize((V, F), mode)
    assert result.success and result.certificate.valid and result.recovery is None
    assert result.max_constraint_violation < 1e-8
    assert result.iterations <= 150


def _start_below_floors(V, F, mode):
    """The shares of the default start's triangles below the area floor and of its corners below
    their floors, as the angle modes' solve sees them (the repaired mesh, the angle modes' gauge)."""
    from sphere_nlp import solve
    from sphere_nlp.repair import prepare_mesh
    from sphere_nlp.starts import initial_point
    from sphere_nlp.targets import make_targets
    prepared = prepare_mesh(np.asarray(V, float), np.asarray(F))
    c = prepared.connectivity
    targets = make_targets(mode, prepared.normalised_vertices, prepared.faces, c.vertex_degree)
    initial = initial_point(c, targets, "auto", prepared.normalised_vertices, DEFAULT_SETTINGS.start_gauge)
    log_u_floor, log_e_floor = solve.floor_bounds(targets, DEFAULT_SETTINGS)
    with np.errstate(divide="ignore", invalid="ignore"):
        triangles = np.mean(np.log(initial.excess) < log_e_floor)
        corners = np.mean(~(solve._log_u(initial.angles, initial.excess) >= log_u_floor))
    return triangles, corners, solve.unplaceable_start(initial, targets, DEFAULT_SETTINGS)


def test_an_unplaceable_start_maps_with_the_area_mode_instead():
    """Where the start's limbs shrink past double precision (solve.unplaceable_start), the angle
    mode's run maps with the matching area mode's route from the same start, certified, and says
    so. On this small body (0.9% and 0.08% of its corners below their floors, under the default
    1.5%) the rule is made to fire by a lower share."""
    from sphere_nlp.cli import summary_line
    V, F = limbed_body(**COLLAPSING_LIMBS)
    triangles, corners, fires = _start_below_floors(V, F, "equal-angles")
    assert triangles >= DEFAULT_SETTINGS.floor_crowd_share and 0.005 <= corners < 0.015 and not fires
    result = parameterize((V, F), "equal-angles", settings=DEFAULT_SETTINGS.replace(unplaceable_corner_share=0.005))
    assert result.success and result.certificate.valid and result.usability()["valid"]
    assert result.target == "equal-areas" and result.area_route["instead_of"] == "equal-angles"
    assert result.area_route["start"].startswith("conformal")
    share = signed_solid_angles(result.vertices, result.faces) / (4 * np.pi / len(result.faces))
    assert share.min() > 1e-3                                  # no limb shrunk past what doubles hold
    assert "equal-areas instead of equal-angles" in summary_line("out.off", result)
    assert result.report()["area_route"]["instead_of"] == "equal-angles"
    # The equal-areas mode's own map: its route started from the surface's conformal map, as that
    # mode does (the equal-angles start is conformal to 2 pi / deg instead).
    np.testing.assert_allclose(result.vertices, parameterize((V, F), "equal-areas").vertices, atol=1e-12)
    # original-angles (4 of its 5,280 corners below their floors): the route starts from the same
    # map and lands where original-areas does.
    result = parameterize((V, F), settings=DEFAULT_SETTINGS.replace(unplaceable_corner_share=0.0005))
    assert result.certificate.valid and result.target == "original-areas"
    assert result.area_route["instead_of"] == "original-angles"
    own = parameterize((V, F), "original-areas").distortion()["mean_abs_log_area"]
    assert result.distortion()["mean_abs_log_area"] <= max(0.03, 1.5 * own)


def test_placeable_limbs_keep_the_angle_modes():
    # human_woman's fingers and the six-legged body: floor-crowded starts, no corner below its floor.
    path = ROOT.parent / "shared" / "meshes" / "human_woman.obj"
    bodies = [limbed_body(**LIMBED_BODIES["27k"])]
    if path.exists():
        import trimesh
        mesh = trimesh.load(path, process=False, force="mesh")
        bodies.append((mesh.vertices, mesh.faces))
    for V, F in bodies:
        for mode in ("original-angles", "equal-angles"):
            _, corners, fires = _start_below_floors(V, F, mode)
            assert corners < 0.005 and not fires


@pytest.mark.slow
@pytest.mark.parametrize("body", ["27k", "31k"])
def test_the_thin_bodies_rule_tells_the_tailed_one_from_the_placeable_one(body):
    # thin:27k (legs of 20-45 radii) is solved in the angle modes; thin:31k adds a tail of 60 radii
    # that no double can hold conformally, and the default mode maps it with original-areas.
    V, F = limbed_body(**THIN_LIMBED_BODIES[body])
    _, corners, fires = _start_below_floors(V, F, "original-angles")
    assert fires == (body == "31k")
    assert (corners >= 0.015) if body == "31k" else (corners < 0.005)
    if body == "31k":
        result = parameterize((V, F))
        assert result.success and result.certificate.valid and result.usability()["valid"]
        assert result.target == "original-areas" and result.area_route["instead_of"] == "original-angles"
        assert result.distortion()["mean_abs_log_area"] <= 0.03


# The area modes on the fingered and the eight-legged bodies (27k; 31k and 50k with a tail of 60
# radii, whose conformal start is valid only after rounds of untangling, and whose descent needs its
# extra steps): the authalic route's promise.
@pytest.mark.slow
@pytest.mark.parametrize("body", ["fingered", "27k", "31k", "50k"])
def test_thin_and_fingered_bodies_reach_the_area_modes_promise(body):
    V, F = limbed_body(**(FINGERED_BODY if body == "fingered" else THIN_LIMBED_BODIES[body]))
    original = parameterize((V, F), "original-areas")
    assert original.certificate.valid
    assert original.distortion()["mean_abs_log_area"] <= 0.03
    equal = parameterize((V, F), "equal-areas")
    assert equal.certificate.valid
    share = signed_solid_angles(equal.vertices, equal.faces) / (4 * np.pi / len(equal.faces))
    assert share.min() >= 0.1


def test_the_angle_modes_hessian_changes_the_path_not_the_optimum():
    # The clipped-corners Hessian (the angle modes' default) leaves out only terms that vanish at a
    # KKT point: from the same start it reaches the exact Hessian's optimum, certified, in no more
    # iterations on a limbed body whose start is far from it (docs/tuning.md, "angle_mode_hessian").
    V, F = limbed_body(n_limbs=4, subdivisions=3, radius=0.3, length_ratios=(10, 20))
    runs = {hessian: parameterize((V, F), settings=DEFAULT_SETTINGS.replace(angle_mode_hessian=hessian))
            for hessian in ("exact", "clipped-corners")}
    assert DEFAULT_SETTINGS.angle_mode_hessian == "clipped-corners"
    for result in runs.values():
        assert result.certificate.valid and result.max_constraint_violation < 1e-8
    assert runs["clipped-corners"].objective == pytest.approx(runs["exact"].objective, rel=1e-7)
    assert runs["clipped-corners"].iterations <= runs["exact"].iterations


def test_semidefinite_tip_blocks_change_the_path_not_the_optimum(monkeypatch):
    # Four limbs of 20-30 radii: their tips go below 1e-16 of their share, whose Hessian blocks are
    # handed to IPOPT positive semidefinite (settings.semidefinite_block_share). The KKT points do
    # not change: the same optimum as with the exact blocks, certified (docs/tuning.md).
    from sphere_nlp import nlp

    projected = []
    project = nlp.nearest_semidefinite_blocks
    monkeypatch.setattr(nlp, "nearest_semidefinite_blocks", lambda blocks: projected.append(blocks.shape[1])
                        or project(blocks))
    V, F = limbed_body(n_limbs=4, subdivisions=3, radius=0.15, length_ratios=(20, 30))
    assert DEFAULT_SETTINGS.semidefinite_block_share == 1e-16
    runs = {share: parameterize((V, F), settings=DEFAULT_SETTINGS.replace(semidefinite_block_share=share))
            for share in (1e-16, 0.0)}
    assert projected                                     # the default run projected some blocks
    for result in runs.values():
        assert result.certificate.valid and result.max_constraint_violation < 1e-8
    assert runs[1e-16].objective == pytest.approx(runs[0.0].objective, rel=1e-7)


def test_a_floor_crowded_start_gets_the_adaptive_barrier_and_keeps_its_optimum(monkeypatch):
    # Four limbs of 45-60 radii: over a fifth of the start's triangles lie below the area floor, and
    # the first margin run gets settings.floor_crowd_margin_options (IPOPT's adaptive barrier); a
    # round body keeps the small monotone barrier. The barrier changes the path, not the optimum.
    from sphere_nlp import solve

    first_options = []
    run_ipopt = solve.run_ipopt

    def spy(nlp, name, x, settings, stages=None, **keywords):
        if name == "margin":
            first_options.append(dict(keywords.get("options") or {}))
        return run_ipopt(nlp, name, x, settings, stages, **keywords)

    monkeypatch.setattr(solve, "run_ipopt", spy)
    V, F = limbed_body(**COLLAPSING_LIMBS)
    monotone = DEFAULT_SETTINGS.replace(floor_crowd_margin_options={"mu_init": 1e-4})
    runs = [parameterize((V, F), settings=settings) for settings in (DEFAULT_SETTINGS, monotone)]
    assert [options.get("mu_strategy") for options in first_options] == ["adaptive", None]
    for result in runs:
        assert result.certificate.valid and result.max_constraint_violation < 1e-8
    assert runs[0].objective == pytest.approx(runs[1].objective, rel=1e-7)
    first_options.clear()
    parameterize(ellipsoid(2))
    assert first_options[0].get("mu_strategy") is None and first_options[0]["mu_init"] == 1e-6
