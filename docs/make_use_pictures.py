"""Draw the pictures of docs/use-the-map.md from the shared meshes.

    PYTHONPATH=. python docs/make_use_pictures.py [--meshes ../shared/meshes] [--spheres /tmp/spheres]

Each mesh is mapped once in the mode that suits its use and its sphere kept in ``--spheres`` (reused
when present; never in the project): max_planck original-areas for resampling (uniform sampling needs
kept areas) and for the spherical harmonics spot original-areas too; max_planck and nefertiti
original-angles for transfer and morph (kept angles keep features' shapes). Meshes are drawn upright
(:func:`sphere_nlp.picture.detect_up`) and seen from the front. Writes docs/use-resample.png,
docs/use-transfer.png, docs/use-morph.png and docs/use-spharm.png (1200 px wide or more, 440 px tall),
and prints the numbers quoted on the page.
"""

import argparse
import sys
from pathlib import Path

import numpy as np

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from sphere_nlp.mesh_io import write_mesh
from sphere_nlp.picture import align_sphere_to_mesh, detect_up, upright_rotation
from sphere_nlp.resample import (align_spheres, draw_mesh, geometry_image, hausdorff, load_map,
                                 morph_frames, resample_icosphere, transfer, write_strip)
from sphere_nlp.shapes import icosphere
from sphere_nlp.spharm import spharm_coefficients, spharm_reconstruct

DOCS = Path(__file__).resolve().parent
# (elevation, azimuth) around the upright mesh, a little from above: from -Y, where nefertiti (+Z up)
# faces, and max_planck and spot (+Y up, facing -Z) face once turned about the vertical (TURN); spot
# from its front left. The light comes from the camera's side (sphere_nlp.resample.draw_mesh).
FRONT, COW_SIDE = (10, -90), (15, -55)
TURN = np.diag([-1.0, -1.0, 1.0])
HEIGHT = 4.4                 # inches at 100 dpi: 440-pixel panels


def cached_map(mesh, spheres, target):
    """(X, S, F) of ``mesh`` mapped in ``target`` mode, the sphere cached in ``spheres``."""
    sphere = spheres / ("%s.%s.sphere.off" % (mesh.stem, target))
    if not sphere.exists():
        X, S, F = load_map(mesh, None, say=lambda line: print(line, file=sys.stderr), target=target)
        write_mesh(sphere, S, F)
    return load_map(mesh, sphere)


def upright(X, F, up=None):
    """The rotation drawing the mesh's up axis (detected unless given) up."""
    return upright_rotation(detect_up(X, F) if up is None else up)


def sphere_beside(X, S, F, R):
    """The sphere turned so each vertex points where it is on the upright mesh (only for drawing)."""
    return S @ (R @ align_sphere_to_mesh(X, S)).T


def panel_row(path, panels, widths=None):
    """Save a row of (title, V, F, per-face colours or None, view) panels (V already upright), or of
    (title, image) panels, 440 px tall and at least 1200 px wide."""
    widths = widths or [1] * len(panels)
    fig = plt.figure(figsize=(max(12.0, 3.2 * sum(widths)), HEIGHT), dpi=100)
    grid = fig.add_gridspec(1, len(panels), width_ratios=widths)
    for k, panel in enumerate(panels):
        if len(panel) == 2:
            ax = fig.add_subplot(grid[k])
            ax.imshow(panel[1])
            ax.set_axis_off()
        else:
            ax = fig.add_subplot(grid[k], projection="3d")
            draw_mesh(ax, panel[1], panel[2], panel[3])
            ax.view_init(*panel[4])
        ax.set_title(panel[0], fontsize=12)
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

    # Resample: max_planck, original-areas map, onto icosphere 4 and 5, and its geometry image.
    X, S, F = cached_map(meshes / "max_planck.obj", spheres, "original-areas")
    R = TURN @ upright(X, F)
    diag = np.linalg.norm(np.ptp(X, axis=0))
    remeshes = {}
    for level in (4, 5, 6):
        remeshes[level] = resample_icosphere(X, S, F, level)
        h, mean = hausdorff((X, F), remeshes[level])
        print("max_planck original-areas, icosphere %d (%d vertices): Hausdorff %.2f%% of the diagonal, "
              "mean distance %.3f%%" % (level, len(remeshes[level][0]), 100 * h / diag, 100 * mean / diag))
    image = geometry_image(X, S, F, 256)
    rgb = (image - image.reshape(-1, 3).min(axis=0)) / np.ptp(image.reshape(-1, 3), axis=0)
    panel_row(DOCS / "use-resample.png",
              [("max_planck (%d vertices)" % len(X), X @ R.T, F, None, FRONT)]
              + [("on icosphere %d (%d vertices)" % (level, len(remeshes[level][0])),
                  remeshes[level][0] @ R.T, remeshes[level][1], None, FRONT) for level in (4, 5)]
              + [("geometry image", rgb)], widths=[1, 1, 1, 1.6])

    # Transfer: colours painted on max_planck by position, read on nefertiti through the aligned spheres.
    A = cached_map(meshes / "max_planck.obj", spheres, "original-angles")
    B = cached_map(meshes / "nefertiti.obj", spheres, "original-angles")
    R_AB = align_spheres(A, B)
    XA, SA, FA = A
    XB, SB, FB = B
    colour_A = (XA - XA.min(axis=0)) / np.ptp(XA, axis=0)
    colour_B = transfer(colour_A, A, B, R_AB)
    face = lambda c, faces: c[faces].mean(axis=1)
    RA, RB = TURN @ upright(XA, FA), upright(XB, FB)
    turn_A = RA @ align_sphere_to_mesh(XA, SA)               # A's sphere as drawn; B's sphere turned alike
    panel_row(DOCS / "use-transfer.png",
              [("max_planck, painted by position", XA @ RA.T, FA, face(colour_A, FA), FRONT),
               ("its sphere", SA @ turn_A.T, FA, face(colour_A, FA), FRONT),
               ("nefertiti's sphere, aligned", SB @ (turn_A @ R_AB.T).T, FB, face(colour_B, FB),
                FRONT),
               ("nefertiti, colours transferred", XB @ RB.T, FB, face(colour_B, FB), FRONT)])

    # Morph: max_planck to nefertiti on max_planck's connectivity, nefertiti fitted onto max_planck.
    frames = morph_frames(A, B, 6, R_AB, fit=True)
    write_strip(DOCS / "use-morph.png", [V @ RA.T for V in frames], FA, view=FRONT, up="z")   # drawn as A

    # SPHARM: spot from an original-areas map, reconstructed at a few degrees on icosphere 5.
    XS, SS, FS = cached_map(meshes / "spot.obj", spheres, "original-areas")
    RS = TURN @ upright(XS, FS)                               # spot faces -Z, as max_planck
    P, G = icosphere(5)
    panels = [("spot (%d vertices)" % len(XS), XS @ RS.T, FS, None, COW_SIDE)]
    for degree in (4, 8, 16):
        V = spharm_reconstruct(spharm_coefficients(XS, SS, FS, degree), P)
        h, mean = hausdorff((XS, FS), (V, G))
        diag = np.linalg.norm(np.ptp(XS, axis=0))
        print("spot SPHARM degree %d: Hausdorff %.1f%% of the diagonal, mean distance %.2f%%"
              % (degree, 100 * h / diag, 100 * mean / diag))
        panels.append(("up to degree %d" % degree, V @ RS.T, G, None, COW_SIDE))
    panel_row(DOCS / "use-spharm.png", panels)


if __name__ == "__main__":
    main()
