"""Reproduce the paper's figures: ``python -m sphere_nlp reproduce fig3 --out DIR``.

Fig. 3 of Sheffer, Gotsman & Dyn (2004) maps a closed cylinder onto the sphere six ways:
(a) the cylinder itself, (b) Alexa's relaxation, and sphere_nlp aiming for (c) equal angles,
(d) equal areas, (e) the original angles, (f) the original areas, with one triangle painted black in
every panel. The paper's findings: (c) looks very like (b); in (d) skinny triangles start to appear;
in (e) the black triangle stays right-angled; in (f) the cap triangles get much larger areas.

:func:`reproduce_fig3` writes ``fig3.png`` (the six panels), ``fig3_a.off`` ... ``fig3_f.off`` (the
meshes) and ``fig3.json`` (the numbers behind the findings, one object per panel; see
:func:`panel_metrics`), all together at the end: an interrupted run writes nothing.
"""

import time
from pathlib import Path

import numpy as np

from . import errors, geometry
from .baselines import alexa_relaxation
from .certify import signed_solid_angles, spherical_angles
from .mesh_io import atomic_output, created_folder, output_transaction, write_json, write_mesh
from .shapes import cylinder

SEGMENTS, RINGS = 12, 6            # the cylinder of models/cylinder.off
SIDE_TRIANGLES = 2 * SEGMENTS * RINGS
# The black triangle: the first triangle of the rectangle row just above the cylinder's middle, a
# right triangle (corners 32.8, 90, 57.2 degrees: the side rectangles are 0.52 wide, 1/3 high).
BLACK_TRIANGLE = (RINGS // 2) * 2 * SEGMENTS

# (panel, method, target, caption)
FIG3_PANELS = (
    ("a", "input", None, "(a) original mesh"),
    ("b", "alexa", None, "(b) Alexa's method"),
    ("c", "sphere_nlp", "equal-angles", "(c) equal angles"),
    ("d", "sphere_nlp", "equal-areas", "(d) equal areas"),
    ("e", "sphere_nlp", "original-angles", "(e) original angles"),
    ("f", "sphere_nlp", "original-areas", "(f) original areas"),
)

# Camera of every panel (degrees): slightly from above, so the top cap shows as well as the side.
VIEW_ELEVATION, VIEW_AZIMUTH = 20.0, -60.0


def panel_metrics(vertices, faces, positions=None):
    """The Fig. 3 numbers of one panel.

    Parameters
    ----------
    vertices : (n, 3) float array
        The 3D cylinder.
    faces : (t, 3) int array
        Its triangles: side triangles first, then the two cap fans (as :func:`shapes.cylinder`).
    positions : (n, 3) float array, optional
        Sphere positions of the vertices. Without them the numbers describe the 3D mesh itself
        (panel (a)): its own corner angles, and its areas scaled to total 4 pi.

    Returns
    -------
    dict
        ``mean_abs_angle_diff_deg``: mean |chord-triangle corner angle - 3D corner angle|, where the
        chord triangle is the straight triangle between the three sphere points; ``mean_abs_log_area``:
        mean |log(spherical area / 3D area scaled to total 4 pi)| (None if a triangle is flipped);
        ``area_cv``: standard deviation / mean of the triangle areas; ``min_angle_deg``: smallest
        spherical corner angle; ``min_side_angle_deg``: the same over the side triangles only;
        ``black_triangle_angles_deg``: the black triangle's three spherical angles, in face order;
        ``cap_area_share``: fraction of the total area covered by the cap triangles.

    Examples
    --------
    >>> V, F = cylinder(SEGMENTS, RINGS)
    >>> m = panel_metrics(V, F)
    >>> m["mean_abs_angle_diff_deg"], m["black_triangle_angles_deg"]
    (0.0, [32.779533, 90.0, 57.220467])
    """
    angles_3d = geometry.corner_angles(vertices, faces)
    areas_3d = geometry.triangle_areas(vertices, faces)
    target_areas = 4 * np.pi * areas_3d / areas_3d.sum()
    if positions is None:
        chord_angles = corner_angles = angles_3d
        areas = target_areas
    else:
        chord_angles = geometry.corner_angles(positions, faces)
        corner_angles = spherical_angles(positions, faces)
        areas = signed_solid_angles(positions, faces)
    log_area = np.abs(np.log(areas / target_areas)) if (areas > 0).all() else None

    def deg(x):
        return round(float(np.degrees(x)), 6)

    return {
        "mean_abs_angle_diff_deg": deg(np.mean(np.abs(chord_angles - angles_3d))),
        "mean_abs_log_area": None if log_area is None else round(float(log_area.mean()), 6),
        "area_cv": round(float(areas.std() / areas.mean()), 6),
        "min_angle_deg": deg(corner_angles.min()),
        "min_side_angle_deg": deg(corner_angles[:SIDE_TRIANGLES].min()),
        "black_triangle_angles_deg": [deg(a) for a in corner_angles[BLACK_TRIANGLE]],
        "cap_area_share": round(float(areas[SIDE_TRIANGLES:].sum() / areas.sum()), 6),
    }


def _view_aligned(points, axis_from, axis_to, facing):
    """Rotate ``points`` so the axis ``axis_from -> axis_to`` is +z and ``facing`` faces the camera.

    A rotation changes no angle or area, so the panels' numbers are unaffected; it only makes every
    panel show the cylinder's axis upright and the black triangle in front.
    """
    axis = axis_to - axis_from
    axis /= np.linalg.norm(axis)
    u = facing - (facing @ axis) * axis
    u /= np.linalg.norm(u)
    v = np.cross(axis, u)
    az = np.radians(VIEW_AZIMUTH)
    toward_camera = np.array([np.cos(az), np.sin(az), 0.0])
    sideways = np.array([-np.sin(az), np.cos(az), 0.0])
    return np.outer(points @ u, toward_camera) + np.outer(points @ v, sideways) + np.outer(points @ axis,
                                                                                            [0, 0, 1])


def _draw_panel(ax, points, faces):
    """Draw the front-facing triangles, edges visible, the black triangle filled black."""
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    el, az = np.radians(VIEW_ELEVATION), np.radians(VIEW_AZIMUTH)
    eye = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    P = points[faces]
    normals = np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    # Both shapes are convex, so the front-facing triangles never overlap on screen: drawing only
    # them avoids mplot3d's per-polygon depth sorting errors.
    front = np.flatnonzero(normals @ eye > 1e-9)
    light = eye + np.array([0.3, 0.0, 0.5])
    light /= np.linalg.norm(light)
    shade = 0.55 + 0.4 * np.clip(normals[front] @ light, 0, 1)
    colours = np.c_[shade, shade, shade, np.ones_like(shade)]
    colours[front == BLACK_TRIANGLE] = (0, 0, 0, 1)
    ax.add_collection3d(Poly3DCollection(P[front], facecolors=colours, edgecolors=(0.1, 0.1, 0.1, 1),
                                         linewidths=0.6))
    ax.set_xlim(-1, 1)
    ax.set_ylim(-1, 1)
    ax.set_zlim(-1, 1)
    ax.set_box_aspect((1, 1, 1), zoom=1.15)    # the empty corners of the box need no room
    ax.view_init(elev=VIEW_ELEVATION, azim=VIEW_AZIMUTH)
    ax.set_axis_off()


def render_fig3(path, vertices, faces, panel_positions):
    """Write the 2 x 3 figure of the six panels as PNG (offscreen, Agg).

    ``panel_positions`` maps panel letters to (n, 3) positions; panel "a" should be the 3D mesh.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    bottom, top = len(vertices) - 2, len(vertices) - 1      # the cap centres
    fig = Figure(figsize=(12, 8), dpi=100)
    FigureCanvasAgg(fig)
    for index, (panel, _, _, caption) in enumerate(FIG3_PANELS):
        row, column = divmod(index, 3)
        X = panel_positions[panel]
        # Fixed boxes, caption under each: 3D axes place their titles unreliably.
        ax = fig.add_axes((column / 3, 0.5 * (1 - row) + 0.06, 1 / 3, 0.44), projection="3d")
        points = _view_aligned(X, X[bottom], X[top], X[faces[BLACK_TRIANGLE]].mean(axis=0))
        _draw_panel(ax, points, faces)
        fig.text(column / 3 + 1 / 6, 0.5 * (1 - row) + 0.05, caption, ha="center", fontsize=13)
    with atomic_output(path, "wb") as out:
        fig.savefig(out, format="png")


def reproduce_fig3(out_dir, progress=None, all_certified=False):
    """Compute, measure, draw and write the six panels of Fig. 3 into ``out_dir``.

    Writes ``fig3.png``, ``fig3_<panel>.off`` for every certified panel (an uncertified sphere is
    never written) and ``fig3.json``, renamed into place together once all are done
    (:func:`~sphere_nlp.mesh_io.output_transaction`): on an exception or a signal nothing is written,
    and a folder this call created is removed again.

    Parameters
    ----------
    out_dir : str or Path
        Created if missing.
    progress : callable(str), optional
        Receives one line per panel.
    all_certified : bool
        Raise :class:`~sphere_nlp.errors.CertificateError` naming the panels whose sphere failed,
        and write nothing, instead of writing the figure with those panels.

    Returns
    -------
    list of dict
        The contents of ``fig3.json``: per panel ``panel``, ``method``, ``target``, ``valid``,
        ``time_s`` and the numbers of :func:`panel_metrics`, plus ``iterations`` and (for (b))
        ``converged``.
    """
    with created_folder(out_dir) as out_dir, output_transaction():     # every file, or none
        records = _fig3_files(out_dir, progress)
        failed = [r["panel"] for r in records if not r["valid"]]
        if all_certified and failed:
            raise errors.CertificateError("panel(s) %s not certified" % ", ".join(failed))
        return records


def _fig3_files(out_dir, progress):
    """The work of :func:`reproduce_fig3`, its files written inside the caller's transaction."""
    from .api import parameterize

    vertices, faces = cylinder(SEGMENTS, RINGS)
    panel_positions, records = {}, []
    for panel, method, target, caption in FIG3_PANELS:
        record = {"panel": panel, "method": method, "target": target}
        if method == "input":
            positions, metrics = vertices, panel_metrics(vertices, faces)
            record.update(valid=True, time_s=0.0)     # the 3D mesh is valid by convention
        elif method == "alexa":
            clock = time.perf_counter()
            relaxed = alexa_relaxation(vertices, faces)
            record.update(valid=relaxed.certificate.valid, time_s=round(time.perf_counter() - clock, 4),
                          iterations=relaxed.iterations, converged=relaxed.converged)
            positions = relaxed.positions
            metrics = panel_metrics(vertices, faces, positions)
        else:
            # The paper's objective (9) verbatim: every corner weighed alike.
            result = parameterize((vertices, faces), target=target, check=False, corner_weighting="uniform")
            record.update(valid=bool(result.success), time_s=round(result.timings["total"], 4),
                          iterations=result.iterations)
            positions = result.vertices
            metrics = panel_metrics(vertices, faces, positions) if result.success else {}
        record.update(metrics)
        records.append(record)
        panel_positions[panel] = positions
        if record["valid"]:
            write_mesh(out_dir / ("fig3_%s.off" % panel), positions, faces)
        if progress:
            progress("%s: %s, %s, %.2f s" % (caption, "certified" if record["valid"] else "NOT CERTIFIED",
                                             "%d iterations" % record.get("iterations", 0),
                                             record["time_s"]))
    render_fig3(out_dir / "fig3.png", vertices, faces, panel_positions)
    write_json(out_dir / "fig3.json", records)
    return records


FIGURES = {"fig3": reproduce_fig3}


def main(argv=None):
    """``python -m sphere_nlp reproduce FIGURE [--out DIR]``; exit 0 when every panel is certified, 1
    (nothing written) when one is not."""
    from .commands import check_output_folder, run_subcommand, subcommand_parser

    parser = subcommand_parser(
        "reproduce",
        description="Reproduce a figure of Sheffer, Gotsman & Dyn (2004): writes the figure as PNG, "
                    "its meshes and its numbers as JSON.")
    parser.add_argument("figure", choices=sorted(FIGURES), help="which figure")
    parser.add_argument("--out", default=".", metavar="DIR", help="output folder (default: .)")
    parser.add_argument("-q", "--quiet", action="store_true", help="print only errors")

    def check(args):
        check_output_folder("--out", args.out)

    def body(args, say):
        # A panel that fails its certificate fails the run: exit 1, nothing written.
        FIGURES[args.figure](args.out, progress=say, all_certified=True)
        say("wrote %s" % (Path(args.out) / ("%s.png" % args.figure)))
        return 0

    return run_subcommand(parser, argv, body, check=check, interrupted="nothing written")
