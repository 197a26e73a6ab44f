"""Point location, resampling, alignment, transfer and morphing through sphere maps (closed forms)."""

from pathlib import Path

import numpy as np
import pytest

from sphere_nlp.api import parameterize
from sphere_nlp.certify import certify
from sphere_nlp.cli import main
from sphere_nlp.locate import SphereLocator
from sphere_nlp.mesh_io import load_mesh, write_mesh
from sphere_nlp.resample import (align_spheres, correspond, geometry_image, grid_directions, hausdorff,
                                 morph_frames, resample_at, resample_icosphere, transfer)
from sphere_nlp.shapes import icosphere
from tests.meshgen import ellipsoid

MODELS = Path(__file__).resolve().parents[1] / "models"


def rotation(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def bumpy(S):
    """An asymmetric shape over the sphere: no rotation maps it onto itself."""
    x, y, z = S.T
    return np.c_[x + 0.3 * y ** 2, 1.6 * y + 0.25 * z ** 2, 0.7 * z + 0.2 * x ** 2 + 0.1 * x * y]


def perturbed_sphere(level=3, seed=0):
    """A certified sphere mesh with irregular triangles (icosphere vertices moved a little)."""
    S, F = icosphere(level)
    S = S + 0.16 * 2.0 ** -level * np.random.default_rng(seed).normal(size=S.shape)
    S /= np.linalg.norm(S, axis=1, keepdims=True)
    assert certify(S, F).valid
    return S, F


def test_locate_every_query_barycentrics_reconstruct():
    S, F = perturbed_sphere(3)
    rng = np.random.default_rng(1)
    Q = rng.normal(size=(5000, 3))
    Q = np.vstack([Q / np.linalg.norm(Q, axis=1, keepdims=True), S[:50]])   # vertices: on edges
    face, bary = SphereLocator(S, F).locate(Q)
    assert (face >= 0).all() and (face < len(F)).all()
    assert (bary >= 0).all() and (bary <= 1).all() and np.allclose(bary.sum(axis=1), 1, atol=1e-12)
    P = np.einsum("ij,ijk->ik", bary, S[F[face]])
    assert np.abs(P / np.linalg.norm(P, axis=1, keepdims=True) - Q).max() < 1e-12


def test_locate_fallback_finds_queries_with_few_candidates():
    S, F = perturbed_sphere(2)
    Q = np.random.default_rng(2).normal(size=(300, 3))
    face, bary = SphereLocator(S, F).locate(Q, k=(1,))        # most need the all-triangle fallback
    P = np.einsum("ij,ijk->ik", bary, S[F[face]])
    Q = Q / np.linalg.norm(Q, axis=1, keepdims=True)
    assert np.abs(P / np.linalg.norm(P, axis=1, keepdims=True) - Q).max() < 1e-12


def test_resampling_a_sphere_returns_the_sphere():
    S, F = perturbed_sphere(4)
    V, G = resample_icosphere(S, S, F, 3)
    r = np.linalg.norm(V, axis=1)
    # Points on flat triangles: inside by at most the chord sag of edges ~ 0.1 rad, 1 - cos(0.05).
    assert r.max() <= 1 + 1e-12 and r.min() > 1 - 2e-3
    assert np.abs(V / r[:, None] - icosphere(3)[0]).max() < 1e-12
    h, _ = hausdorff((S, F), (V, G), samples=20000)
    assert h < 0.05


def test_resampling_cylinder_at_its_sphere_vertices_returns_its_vertices():
    # The shipped cylinder's own map, read at its own sphere vertices: the input, to round-off.
    result = parameterize(str(MODELS / "cylinder.off"))
    X, S = result.input_vertices, result.vertices
    assert np.abs(resample_at(X, S, result.faces, S) - X).max() < 1e-9


def test_geometry_image_grids_are_unit_and_cover():
    for layout, shape in (("equirectangular", (8, 16, 3)), ("octahedral", (16, 16, 3))):
        D = grid_directions(8 if layout == "equirectangular" else 16, layout)
        assert D.shape == shape and np.allclose(np.linalg.norm(D, axis=-1), 1)
    S, F = icosphere(3)
    image = geometry_image(3 * S, S, F, 16, "octahedral")
    assert image.shape == (16, 16, 3) and np.abs(np.linalg.norm(image, axis=-1) - 3).max() < 0.02


@pytest.mark.parametrize("use_landmarks", [True, False])
def test_correspondence_with_rotated_copy_is_the_rotation(use_landmarks):
    S, F = perturbed_sphere(3)
    X = bumpy(S)
    Q = rotation([1, 2, 3], 0.9)                  # the shape's rotation
    R0 = rotation([-2, 1, 0.5], 2.1)              # B's sphere: an arbitrary orientation of A's
    XB = X @ Q.T + [0.5, -1, 2]
    A, B = (X, S, F), (XB, S @ R0.T, F)
    landmarks = [(i, i) for i in (0, 7, 30, 100)] if use_landmarks else None
    R = align_spheres(A, B, landmarks)
    assert np.abs(R - R0).max() < 1e-9
    Y, _, _ = correspond(A, B, R)
    assert np.abs(Y - XB).max() < 1e-9


def test_transferred_linear_field_stays_linear():
    SA, FA = icosphere(4)
    SB, FB = perturbed_sphere(2, seed=3)
    XA, XB = bumpy(SA), bumpy(SB)
    R0 = rotation([0, 1, 1], 0.7)
    A, B = (XA, SA, FA), (XB @ rotation([1, 0, 0], 1.0).T, SB @ R0.T, FB)
    a = np.array([0.3, -1.2, 0.5])
    values = XA @ a + 2.0
    got = transfer(values, A, B, R0)
    assert np.abs(got - (XB @ a + 2.0)).max() < 0.02 * np.ptp(values)
    colours = np.c_[values, 2 * values]
    assert np.allclose(transfer(colours, A, B, R0), np.c_[got, 2 * got])
    labels = (XA[:, 0] > 0).astype(int)
    got_labels = transfer(labels, A, B, R0, kind="nearest")
    far = np.abs(XB[:, 0]) > 0.2
    assert got_labels.dtype == labels.dtype and np.array_equal(got_labels[far], (XB[far, 0] > 0).astype(int))


def test_morph_ends_are_the_resampled_shapes():
    S, F = perturbed_sphere(3)
    XA = ellipsoid(3)[0]                             # on icosphere(3)'s vertices, i.e. over S's order
    SA, FA = icosphere(3)
    A = (XA, SA, FA)
    B = (bumpy(S), S, F)
    frames = morph_frames(A, B, 5, np.eye(3))
    assert len(frames) == 5 and np.array_equal(frames[0], XA)
    Y, _, _ = correspond(A, B, np.eye(3))
    assert np.allclose(frames[-1], Y) and np.allclose(frames[2], (XA + Y) / 2)


def test_cli_resample_and_morph(tmp_path):
    S, F = icosphere(2)
    X = bumpy(S)
    write_mesh(tmp_path / "a.off", X, F)
    write_mesh(tmp_path / "a.sphere.off", S, F)
    out = tmp_path / "r.obj"
    assert main(["resample", str(tmp_path / "a.off"), "--sphere", str(tmp_path / "a.sphere.off"),
                 "--icosphere", "2", "-o", str(out), "-q"]) == 0
    V, G = load_mesh(out)
    assert np.abs(V - X).max() < 1e-9                # same sphere vertices: the input itself
    assert main(["morph", str(tmp_path / "a.off"), str(tmp_path / "a.off"), "--sphere-a",
                 str(tmp_path / "a.sphere.off"), "--sphere-b", str(tmp_path / "a.sphere.off"),
                 "--frames", "3", "--out", str(tmp_path / "m"), "-q"]) == 0
    assert sorted(p.name for p in (tmp_path / "m").iterdir()) == [
        "frame_000.obj", "frame_001.obj", "frame_002.obj", "strip.png"]
    from PIL import Image

    width, height = Image.open(tmp_path / "m" / "strip.png").size
    assert height >= 400 and width >= 3 * 200                   # readable: 240 x 440 pixels a frame


def test_cli_bad_usage_exits_2_before_work(tmp_path, capsys):
    S, F = icosphere(1)
    write_mesh(tmp_path / "a.off", S, F)
    write_mesh(tmp_path / "wrong.off", *icosphere(2))
    assert main(["resample", str(tmp_path / "a.off"), "-o", str(tmp_path / "r.xyz")]) == 2
    assert main(["resample", str(tmp_path / "a.off"), "--sphere", str(tmp_path / "wrong.off"),
                 "-o", str(tmp_path / "r.off")]) == 2
    assert main(["morph", str(tmp_path / "a.off"), str(tmp_path / "a.off"), "--frames", "1",
                 "--out", str(tmp_path / "m")]) == 2
    assert main(["morph", str(tmp_path / "a.off"), str(tmp_path / "a.off"), "--landmarks", "1:2",
                 "--out", str(tmp_path / "m")]) == 2
    assert main(["resample", str(tmp_path / "a.off"), "-o", str(tmp_path / "no" / "r.off")]) == 2
    assert main(["morph", str(tmp_path / "a.off"), str(tmp_path / "a.off"), "--out", str(tmp_path / "a.off")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 6 and all(line.startswith("sphere-nlp ") and "error:" in line for line in err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.off", "wrong.off"]


def test_cli_transfer_labels_and_fields(tmp_path):
    S, F = icosphere(2)
    X = bumpy(S)
    Q = rotation([0, 0, 1], 1.3)
    write_mesh(tmp_path / "a.off", X, F)
    write_mesh(tmp_path / "a.sphere.off", S, F)
    write_mesh(tmp_path / "b.off", X @ Q.T, F)
    write_mesh(tmp_path / "b.sphere.off", S @ rotation([1, 1, 0], 0.4).T, F)
    labels = np.arange(len(X)) % 7
    np.save(tmp_path / "labels.npy", labels)
    common = [str(tmp_path / "a.off"), str(tmp_path / "b.off"), "--sphere-a", str(tmp_path / "a.sphere.off"),
              "--sphere-b", str(tmp_path / "b.sphere.off"), "-q"]
    assert main(["transfer", *common, "--values", str(tmp_path / "labels.npy"), "--kind", "nearest",
                 "-o", str(tmp_path / "out.npy")]) == 0
    assert np.array_equal(np.load(tmp_path / "out.npy"), labels)     # a rotated copy: vertex to vertex
    assert main(["transfer", *common, "--values", str(tmp_path / "labels.npy"), "-o",
                 str(tmp_path / "out.txt")]) == 2
    np.save(tmp_path / "short.npy", labels[:5])
    assert main(["transfer", *common, "--values", str(tmp_path / "short.npy"), "-o",
                 str(tmp_path / "out2.npy")]) == 2
    assert not (tmp_path / "out2.npy").exists()


def test_morph_fit_moves_b_onto_a():
    S, F = icosphere(2)
    X = bumpy(S)
    Q = rotation([1, -1, 2], 0.8)
    frames = morph_frames((X, S, F), (2.5 * X @ Q.T + [1, 2, 3], S, F), 3, np.eye(3), fit=True)
    assert all(np.abs(frame - X).max() < 1e-9 for frame in frames)   # the same shape: nothing moves


def test_spharm_recovers_a_degree_two_shape():
    from sphere_nlp.spharm import real_harmonics, spharm_coefficients, spharm_reconstruct

    S, F = icosphere(4)
    X = bumpy(S)                                   # every coordinate a polynomial of degree <= 2 in p
    c2 = spharm_coefficients(X, S, F, 2)
    c4 = spharm_coefficients(X, S, F, 4)
    P = icosphere(3)[0]
    assert np.abs(spharm_reconstruct(c2, P) - bumpy(P)).max() < 5e-3   # interpolation error only
    assert np.abs(c4[9:]).max() < 5e-3             # nothing above degree 2
    assert np.allclose(c4[:9], c2, atol=5e-3)
    # Degree 1 of x = p_x alone: Y_11 = sqrt(3 / 4 pi) p_x.
    c = spharm_coefficients(S, S, F, 1)
    assert abs(c[3, 0] - np.sqrt(4 * np.pi / 3)) < 5e-3 and abs(c[0, 0]) < 1e-3


def _recording_parameterize(monkeypatch):
    """Every map the subcommands make, recorded as it is returned (the real solve runs)."""
    import sphere_nlp.api as api

    made = []
    real = api.parameterize

    def recording(*args, **kwargs):
        result = real(*args, **kwargs)
        made.append(result)
        return result

    monkeypatch.setattr(api, "parameterize", recording)
    return made


def test_resample_maps_in_an_area_mode_by_default(tmp_path, monkeypatch, capsys):
    made = _recording_parameterize(monkeypatch)
    X, F = ellipsoid(2)
    write_mesh(tmp_path / "e.off", X, F)
    out = tmp_path / "r.off"
    assert main(["resample", str(tmp_path / "e.off"), "--icosphere", "2", "-o", str(out)]) == 0
    assert "(target original-areas)" in capsys.readouterr().err
    [result] = made
    assert result.target == "original-areas" and result.certificate.valid
    assert result.distortion()["mean_abs_log_area"] < 0.01          # every part kept its size
    # The remesh written is the input's shape read through exactly that map.
    V, G = load_mesh(out)
    expected, _ = resample_icosphere(np.asarray(result.input_vertices), result.vertices, result.faces, 2)
    assert np.abs(V - expected).max() < 1e-12


def test_transfer_and_morph_map_in_the_mode_given(tmp_path, monkeypatch, capsys):
    made = _recording_parameterize(monkeypatch)
    X, F = ellipsoid(2)
    write_mesh(tmp_path / "a.off", X, F)
    write_mesh(tmp_path / "b.off", X * [1.2, 0.9, 1.0], F)
    np.save(tmp_path / "v.npy", X[:, 0])
    assert main(["transfer", str(tmp_path / "a.off"), str(tmp_path / "b.off"), "--values", str(tmp_path / "v.npy"),
                 "-o", str(tmp_path / "out.npy"), "--target", "equal-angles"]) == 0
    assert main(["morph", str(tmp_path / "a.off"), str(tmp_path / "b.off"), "--frames", "2", "--out",
                 str(tmp_path / "m"), "--target", "equal-angles"]) == 0
    assert [r.target for r in made] == ["equal-angles"] * 4 and all(r.certificate.valid for r in made)
    assert capsys.readouterr().err.count("(target equal-angles)") == 4
    assert main(["morph", str(tmp_path / "a.off"), str(tmp_path / "b.off"), "--out", str(tmp_path / "n"),
                 "--target", "equal-area"]) == 2                  # a bad mode: refused before mapping
    assert len(made) == 4 and not (tmp_path / "n").exists()


def squeezed_sphere(level=3, factor=30.0):
    """A certified sphere of icosphere(level) that shrinks one hemisphere's triangles by up to
    ``factor``^2 (a Moebius map: stereographic projection, scaled, projected back), as a conformal
    map shrinks a limb."""
    S, F = icosphere(level)
    x, y, z = (S @ rotation([1, 2, 3], 0.3).T).T         # no vertex at the pole projected from
    u, v = factor * x / (1 - z), factor * y / (1 - z)
    r2 = u * u + v * v
    T = np.c_[2 * u / (1 + r2), 2 * v / (1 + r2), (r2 - 1) / (1 + r2)]
    assert certify(T, F).valid
    return T, F


def test_a_given_sphere_that_shrank_parts_gets_the_shrink_line(tmp_path, capsys):
    S, F = icosphere(3)
    T, _ = squeezed_sphere(3)
    write_mesh(tmp_path / "a.off", S, F)
    write_mesh(tmp_path / "a.sphere.off", T, F)
    write_mesh(tmp_path / "round.sphere.off", S, F)
    assert main(["resample", str(tmp_path / "a.off"), "--sphere", str(tmp_path / "a.sphere.off"),
                 "--icosphere", "1", "-o", str(tmp_path / "r.off")]) == 0
    [line] = [x for x in capsys.readouterr().err.splitlines() if "shrank parts of the surface" in x]
    assert str(tmp_path / "a.sphere.off") in line and "--target original-areas" in line
    assert main(["resample", str(tmp_path / "a.off"), "--sphere", str(tmp_path / "round.sphere.off"),
                 "--icosphere", "1", "-o", str(tmp_path / "r2.off")]) == 0
    assert "shrank" not in capsys.readouterr().err


def test_morph_fits_b_onto_a_unless_told_not_to(tmp_path, capsys):
    S, F = icosphere(2)
    X = bumpy(S)
    Q = rotation([1, -1, 2], 0.8)
    write_mesh(tmp_path / "a.off", X, F)
    write_mesh(tmp_path / "b.off", 2.5 * X @ Q.T + [1, 2, 3], F)
    write_mesh(tmp_path / "s.off", S, F)
    common = [str(tmp_path / "a.off"), str(tmp_path / "b.off"), "--sphere-a", str(tmp_path / "s.off"),
              "--sphere-b", str(tmp_path / "s.off"), "--frames", "3", "--landmarks", "0:0,5:5,9:9,20:20"]
    assert main(["morph", *common, "--out", str(tmp_path / "fit")]) == 0
    for k in range(3):                           # the same shape 2.5 times larger: nothing moves
        assert np.abs(load_mesh(tmp_path / "fit" / ("frame_%03d.obj" % k))[0] - X).max() < 1e-6
    assert "size" not in capsys.readouterr().err
    assert main(["morph", *common, "--out", str(tmp_path / "kept"), "--no-fit"]) == 0
    last = load_mesh(tmp_path / "kept" / "frame_002.obj")[0]
    assert np.abs(last - (2.5 * X @ Q.T + [1, 2, 3])).max() < 1e-6
    assert "B is 2.5 times A's size" in capsys.readouterr().err


def pinched_fan(level=3, vertex=100, factor=3e-4):
    """icosphere(level) and a certified sphere of it whose one vertex's fan is shrunk ``factor``
    times across (1e-7 of its area): a small part of the surface collapsed, the rest as it was."""
    S, F = icosphere(level)
    ring = np.unique(F[(F == vertex).any(axis=1)])
    T = S.copy()
    T[ring] = S[vertex] + factor * (S[ring] - S[vertex])
    T /= np.linalg.norm(T, axis=1, keepdims=True)
    assert certify(T, F).valid
    return S, T, F


def test_the_shrink_line_says_what_triggered_it_in_numbers_that_agree():
    from sphere_nlp.metrics import SHRUNK_SHARE, area_log_ratio, normalised_areas_3d, shrinkage_summary

    def measured(X, S, F):
        log_ratio = area_log_ratio(X, S, F)
        small = log_ratio < np.log(SHRUNK_SHARE)
        return float(np.abs(log_ratio).mean()), float(normalised_areas_3d(X, F)[small].sum() / (4 * np.pi)), \
            int(small.sum())

    # Shrunk on average, no triangle below 1e-6 of its share (koala's case): the line speaks of
    # the average alone, never of "0% of its area".
    S, F = icosphere(3)
    T, _ = squeezed_sphere(3)
    mean, fraction, count = measured(S, T, F)
    s = shrinkage_summary(S, T, F, "original-angles")
    assert fraction == 0 and mean > 1 and s["triggers"] == ["mean"]
    assert "%.2f" % mean in s["note"] and "factor %.3g" % np.exp(mean) in s["note"]
    assert "of the surface lies" not in s["note"] and "0%" not in s["note"]
    # A small part collapsed, the average barely moved: the line names the part's share and count.
    X, T, F = pinched_fan()
    mean, fraction, count = measured(X, T, F)
    s = shrinkage_summary(X, T, F, "equal-angles")
    assert mean < 1 and fraction >= 1e-3 and s["triggers"] == ["surface"]
    assert "%.3g%% of the surface" % (100 * fraction) in s["note"] and "(%d triangles" % count in s["note"]
    assert "mean |log area ratio|" not in s["note"]
    # An area mode's map is not judged (it keeps each triangle's share by its targets).
    assert shrinkage_summary(X, T, F, "original-areas")["note"] is None
