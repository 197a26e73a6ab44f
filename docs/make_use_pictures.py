"""Draw the pictures of docs/use-the-map.md from the shared meshes.

    PYTHONPATH=. python docs/make_use_pictures.py [--meshes ../shared/meshes] [--spheres /tmp/spheres]

Each mesh is mapped once in original-angles mode and its sphere kept in ``--spheres`` (reused when
present; never in the project). Writes docs/use-resample.png, docs/use-transfer.png and
docs/use-morph.png and docs/use-spharm.png, and prints the numbers quoted on the page.
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from sphere_nlp.mesh_io import write_mesh
from sphere_nlp.resample import (align_spheres, draw_mesh, geometry_image, hausdorff, load_map,
                                 morph_frames, resample_icosphere, transfer, write_strip)
from sphere_nlp.shapes import icosphere
from sphere_nlp.spharm import spharm_coefficients, spharm_reconstruct

DOCS = Path(__file__).resolve().parent


def cached_map(mesh, spheres):
    sphere = spheres / (mesh.stem + ".sphere.off")
    if not sphere.exists():
        X, S, F = load_map(mesh, None, say=lambda line: print(line, file=sys.stderr))
        write_mesh(sphere, S, F)
    return load_map(mesh, sphere)


def panel_row(path, panels, dpi=80):
    """Save a row of (title, V, F, per-face colours or None, (elev, azim)) panels."""
    fig = plt.figure(figsize=(3.0 * len(panels), 3.2), dpi=dpi)
    for k, (title, V, F, colours, view) in enumerate(panels):
        ax = fig.add_subplot(1, len(panels), k + 1, projection="3d")
        draw_mesh(ax, V, F, colours)
        ax.view_init(*view)
        ax.set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--meshes", default=str(DOCS.parent.parent / "shared" / "meshes"))
    parser.add_argument("--spheres", default="/tmp/sphere_nlp_spheres")
    args = parser.parse_args()
    meshes, spheres = Path(args.meshes), Path(args.spheres)
    spheres.mkdir(parents=True, exist_ok=True)
    head_view = (10, -90)

    # Resample: nefertiti onto an icosphere of level 4, and its equirectangular geometry image.
    X, S, F = cached_map(meshes / "nefertiti.obj", spheres)
    start = time.perf_counter()
    V, G = resample_icosphere(X, S, F, 6)
    print("nefertiti: %d vertices -> icosphere 6 (%d vertices) in %.2f s" % (len(X), len(V), time.perf_counter() - start))
    diag = np.linalg.norm(np.ptp(X, axis=0))
    for level in (4, 5, 6):
        Vl, Gl = resample_icosphere(X, S, F, level)
        h, mean = hausdorff((X, F), (Vl, Gl))
        print("  icosphere %d: Hausdorff %.4g (%.2f%% of diagonal), mean distance %.3g (%.3f%%)"
              % (level, h, 100 * h / diag, mean, 100 * mean / diag))
    V4, G4 = resample_icosphere(X, S, F, 4)
    image = geometry_image(X, S, F, 128)
    rgb = (image - image.reshape(-1, 3).min(axis=0)) / np.ptp(image.reshape(-1, 3), axis=0)
    fig = plt.figure(figsize=(10.5, 3.2), dpi=80)
    for k, (title, VV, FF) in enumerate((("nefertiti (%d vertices)" % len(X), X, F),
                                         ("resampled on icosphere 4 (%d)" % len(V4), V4, G4))):
        ax = fig.add_subplot(1, 3, k + 1, projection="3d")
        draw_mesh(ax, VV, FF)
        ax.view_init(*head_view)
        ax.set_title(title, fontsize=9)
    ax = fig.add_subplot(1, 3, 3)
    ax.imshow(rgb)
    ax.set_title("geometry image (equirectangular, xyz as rgb)", fontsize=9)
    ax.set_axis_off()
    fig.tight_layout()
    fig.savefig(DOCS / "use-resample.png")
    plt.close(fig)

    # Transfer: colours painted on max_planck by position, read on nefertiti through the aligned spheres.
    A = cached_map(meshes / "max_planck.obj", spheres)
    B = (X, S, F)
    start = time.perf_counter()
    R = align_spheres(A, B)
    print("align max_planck -> nefertiti: %.2f s" % (time.perf_counter() - start))
    XA = A[0]
    colour_A = (XA - XA.min(axis=0)) / np.ptp(XA, axis=0)
    colour_B = transfer(colour_A, A, B, R)
    face = lambda c, F: c[F].mean(axis=1)
    panel_row(DOCS / "use-transfer.png",
              [("max_planck, painted by position", XA, A[2], face(colour_A, A[2]), head_view),
               ("nefertiti, colours transferred", X, F, face(colour_B, F), head_view)])

    # Morph: max_planck to nefertiti on max_planck's connectivity.
    frames = morph_frames(A, B, 6, R, fit=True)
    write_strip(DOCS / "use-morph.png", frames, A[2], view=head_view)

    # SPHARM: spot from an original-areas map, reconstructed at a few degrees on icosphere 5.
    mesh = meshes / "spot.obj"
    sphere = spheres / "spot.original-areas.sphere.off"
    if not sphere.exists():
        from sphere_nlp.api import parameterize

        result = parameterize(str(mesh), target="original-areas", max_time=150, on_limit="project")
        write_mesh(sphere, result.vertices, result.faces)
    XS, SS, FS = load_map(mesh, sphere)
    P, G = icosphere(5)
    cow_view = (15, -60)
    panels = [("spot (%d vertices)" % len(XS), XS, FS, None, cow_view)]
    for degree in (4, 8, 16):
        V = spharm_reconstruct(spharm_coefficients(XS, SS, FS, degree), P)
        h, mean = hausdorff((XS, FS), (V, G))
        print("spot SPHARM degree %d: Hausdorff %.3g, mean distance %.3g (diagonal %.3g)"
              % (degree, h, mean, np.linalg.norm(np.ptp(XS, axis=0))))
        panels.append(("degree %d" % degree, V, G, None, cow_view))
    panel_row(DOCS / "use-spharm.png", panels)


if __name__ == "__main__":
    main()
