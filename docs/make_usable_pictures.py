"""Draw docs/usable-cheburashka.png: what the default mode's corner weights and floors change on a
limbed mesh, next to the paper's objective (9) without floors.

    PYTHONPATH=. python docs/make_usable_pictures.py [--mesh ../shared/meshes/cheburashka.off]

The panels show the triangles around the worst triangle of the (9) map (largest quasi-conformal
ratio, 1 = shape kept; outlined): on the input, on the sphere of the (9) map and on the
sphere of the default map, each flattened onto its own tangent plane and coloured by that ratio
(log scale). Titles carry the whole map's figures from :func:`sphere_nlp.metrics.usability_summary`,
which are also printed.
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

DOCS = Path(__file__).resolve().parent
RUNS = (("paper's (9), no floors", dict(corner_weighting="uniform", corner_floor=0, area_floor=0)),
        ("defaults", {}))


def neighbourhood(faces, face, rings=1):
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
    F = results[0][1].faces
    worst = int(np.argmax(results[0][3]))
    patch = neighbourhood(F, worst)
    norm = colors.LogNorm(vmin=1, vmax=1e3)
    panels = [("input (%s)" % Path(args.mesh).name, results[0][1].input_vertices, None)]
    panels += [("%s: QC max %.3g,\n%d corners below 0.1 x target" % (name, use["qc_max"], use["corners_below_fraction"]),
                result.vertices, qc) for name, result, use, qc in results]
    fig, axes = plt.subplots(1, 3, figsize=(11, 4.0), dpi=80)
    for ax, (title, V, qc) in zip(axes, panels):
        used = np.unique(F[patch])
        flat = np.zeros((len(V), 2))
        flat[used] = flatten(V[used])
        facecolors = ("0.85" if qc is None else cm.YlOrRd(norm(np.clip(qc[patch], 1, 1e3))))
        ax.add_collection(PolyCollection(flat[F[patch]], facecolors=facecolors, edgecolors="0.3", linewidths=0.4))
        ax.add_collection(PolyCollection(flat[F[[worst]]], facecolors="none", edgecolors="k", linewidths=1.5))
        ax.autoscale_view()
        ax.set_aspect("equal")
        ax.set_axis_off()
        ax.set_title(title, fontsize=9)
    bar = fig.colorbar(cm.ScalarMappable(norm=norm, cmap="YlOrRd"), ax=axes[1:], shrink=0.8)
    bar.set_label("quasi-conformal ratio per triangle")
    fig.savefig(args.out)
    plt.close(fig)
    print("wrote", args.out)


if __name__ == "__main__":
    main()
