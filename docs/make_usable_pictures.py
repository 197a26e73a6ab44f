"""Draw docs/usable-cheburashka.png: what the default mode's corner weights and floors change on a
limbed mesh, next to the paper's objective (9) without floors.

    PYTHONPATH=. python docs/make_usable_pictures.py [--mesh ../shared/meshes/cheburashka.off]

Four panels, 1400 x 480 pixels: the whole mesh (upright, seen from the side of the worst triangle)
with the worst triangle of the (9) map (largest quasi-conformal ratio) ringed; then the
triangles within two rings of it on the input, on the sphere of the (9) map and on the sphere of the
default map, each flattened onto its own tangent plane and coloured the same way. Titles carry the
whole map's figures from :func:`sphere_nlp.metrics.usability_summary`, which are also printed.
"""

import argparse
import time
from pathlib import Path

import numpy as np

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from matplotlib import cm, colors
from matplotlib.collections import PolyCollection

import sphere_nlp
from sphere_nlp.metrics import quasi_conformal_ratio
from sphere_nlp.picture import camera_direction, detect_up, upright_rotation
from sphere_nlp.resample import draw_mesh

DOCS = Path(__file__).resolve().parent
RUNS = (("paper's (9), no floors", dict(corner_weighting="uniform", corner_floor=0, area_floor=0)),
        ("defaults", {}))
QC_NORM = colors.LogNorm(vmin=1, vmax=1e3)


def neighbourhood(faces, face, rings=2):
    """The faces within ``rings`` edges (vertex rings) of ``face``."""
    vertices = set(faces[face])
    for _ in range(rings):
        near = np.isin(faces, list(vertices)).any(axis=1)
        vertices = set(faces[near].ravel())
    return np.flatnonzero(np.isin(faces, list(vertices)).all(axis=1))


def flatten(points):
    """Points projected onto their best-fit plane, in 2D (centred)."""
    centred = points - points.mean(axis=0)
    _, _, axes = np.linalg.svd(centred, full_matrices=False)
    return centred @ axes[:2].T


def qc_colours(qc):
    return cm.YlOrRd(QC_NORM(np.clip(qc, 1, 1e3)))


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mesh", default=str(DOCS.parent.parent / "shared" / "meshes" / "cheburashka.off"))
    parser.add_argument("--out", default=str(DOCS / "usable-cheburashka.png"))
    args = parser.parse_args()
    results = []
    for name, options in RUNS:
        began = time.perf_counter()
        result = sphere_nlp.parameterize(args.mesh, **options)
        use = result.usability()
        print("%s: QC max %.3g, %d corners below 0.1 x target, smallest triangle %.1e of the mean, mean angle "
              "distortion %.2f deg, %.0f s" % (name, use["qc_max"], use["corners_below_fraction"],
                                               use["min_area_ratio"], use["mean_abs_angle_diff_deg"],
                                               time.perf_counter() - began))
        results.append((name, result, use, quasi_conformal_ratio(result.input_vertices, result.vertices,
                                                                   result.faces)))
    X, F = results[0][1].input_vertices, results[0][1].faces
    worst = int(np.argmax(results[0][3]))
    patch = neighbourhood(F, worst)

    fig = plt.figure(figsize=(14, 4.8), dpi=100)
    grid = fig.add_gridspec(1, 5, width_ratios=[1.2, 1, 1, 1, 0.08])
    # The whole mesh, upright, seen from the side the worst triangle faces.
    R = upright_rotation(detect_up(X, F))
    U = X @ R.T
    normal = np.cross(U[F[worst, 1]] - U[F[worst, 0]], U[F[worst, 2]] - U[F[worst, 0]])
    normal *= np.sign(normal @ (U[F[worst]].mean(axis=0) - U.mean(axis=0)))
    azimuth = np.degrees(np.arctan2(normal[1], normal[0]))
    ax = fig.add_subplot(grid[0], projection="3d", computed_zorder=False)
    draw_mesh(ax, U, F)
    ax.view_init(15, azimuth)
    centre = U[F[worst]].mean(axis=0) + 0.02 * np.ptp(U, axis=0).max() * camera_direction(15, azimuth)
    ax.scatter(*centre, s=500, facecolors="none", edgecolors="k", linewidths=2, zorder=10)
    ax.set_title("%s, the (9) map's\nworst triangle ringed" % Path(args.mesh).name, fontsize=12)

    panels = [("input, around the ringed triangle", X, None)]
    panels += [("%s: QC max %.3g,\n%d corners below 0.1 x target" % (name, use["qc_max"], use["corners_below_fraction"]),
                result.vertices, qc) for name, result, use, qc in results]
    used = np.unique(F[patch])
    for k, (title, V, qc) in enumerate(panels):
        ax = fig.add_subplot(grid[k + 1])
        flat = np.zeros((len(V), 2))
        flat[used] = flatten(V[used])
        facecolors = "0.85" if qc is None else qc_colours(qc[patch])
        ax.add_collection(PolyCollection(flat[F[patch]], facecolors=facecolors, edgecolors="0.3", linewidths=0.4))
        ax.add_collection(PolyCollection(flat[F[[worst]]], facecolors="none", edgecolors="k", linewidths=2))
        ax.autoscale_view()
        ax.set_aspect("equal")
        ax.set_axis_off()
        ax.set_title(title, fontsize=12)
    bar = fig.colorbar(cm.ScalarMappable(norm=QC_NORM, cmap="YlOrRd"), cax=fig.add_subplot(grid[4]))
    bar.set_label("QC: quasi-conformal ratio (1 = shape kept)", fontsize=11)
    fig.tight_layout()
    fig.savefig(args.out)
    plt.close(fig)
    print("wrote", args.out)


if __name__ == "__main__":
    main()
