"""A picture of a spherical map: mesh and sphere coloured by distortion, and the mesh checkerboarded.

:func:`render_png` draws three panels side by side, offscreen (matplotlib's Agg backend, no display
needed):

1. the input mesh, each triangle coloured by a distortion measure of the map
   (:func:`sphere_nlp.metrics.area_log_ratio` or :func:`sphere_nlp.metrics.angle_distortion`);
2. the sphere, coloured the same way, turned to show the same side as panel 1;
3. the input mesh textured with a checkerboard in the sphere's longitude and latitude, the (u, v) of
   :mod:`sphere_nlp.texture`: squares that stay square mean angles are kept, equal sizes mean areas are.

Triangles are drawn flat with Lambert shading; those facing away from the camera are culled and the
rest depth-sorted by mplot3d (painter's algorithm), exact for the sphere and good for most meshes.
Panel 3 splits triangles into 4, 16 or 64 pieces for a finer checkerboard only while the pieces stay
under ``max_faces``, which keeps large meshes fast (every visible triangle is always drawn: leaving
some out would leave holes).
"""

import numpy as np

from .mesh_io import atomic_output

# Camera (degrees) of every panel: a little from above, as in the Fig. 3 reproduction.
VIEW_ELEVATION, VIEW_AZIMUTH = 20.0, -60.0
CHECKER_SQUARES = (16, 8)            # along longitude, along latitude: 22.5-degree squares
CHECKER_COLOURS = np.array([[0.95, 0.93, 0.88], [0.85, 0.25, 0.15]])
MEASURES = {
    "area": ("log(sphere area / mesh area)", "RdBu_r"),
    "angle": ("angle distortion (degrees)", "viridis"),
}


def triangle_measure(mesh_vertices, sphere_vertices, faces, measure="area"):
    """Per-triangle distortion used for colouring, (t,).

    ``"area"``: :func:`sphere_nlp.metrics.area_log_ratio` (0 = the triangle keeps its share of the
    surface; + larger on the sphere). ``"angle"``: the mean over the three corners of
    :func:`sphere_nlp.metrics.angle_distortion`, in degrees.

    Examples
    --------
    >>> from sphere_nlp.shapes import icosphere
    >>> V, F = icosphere(1)
    >>> float(np.abs(triangle_measure(V, V, F, "angle")).max()) < 1e-9
    True
    """
    from .metrics import angle_distortion, area_log_ratio

    if measure == "area":
        return area_log_ratio(mesh_vertices, sphere_vertices, faces)
    if measure == "angle":
        return np.degrees(angle_distortion(mesh_vertices, sphere_vertices, faces).mean(axis=1))
    raise ValueError("measure must be one of %s, got %r" % (", ".join(MEASURES), measure))


def camera_direction(elevation=VIEW_ELEVATION, azimuth=VIEW_AZIMUTH):
    """Unit vector from the scene toward the camera, as mplot3d's ``view_init`` places it."""
    el, az = np.radians(elevation), np.radians(azimuth)
    return np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


def align_sphere_to_mesh(mesh_vertices, sphere_vertices):
    """Rotation R (3, 3) turning the sphere so each vertex points roughly where it is on the mesh.

    The best proper rotation (Kabsch) from the sphere positions to the directions of the centred mesh
    vertices. Only for drawing: a rotation changes no angle or area, and panel 2 then shows the same
    side of the map as panel 1.

    Examples
    --------
    >>> from sphere_nlp.shapes import icosphere
    >>> V, _ = icosphere(1)
    >>> R = align_sphere_to_mesh(3 * V, V)
    >>> bool(np.allclose(R, np.eye(3)))
    True
    """
    centred = mesh_vertices - mesh_vertices.mean(axis=0)
    directions = centred / np.maximum(np.linalg.norm(centred, axis=1, keepdims=True), 1e-300)
    u, _, vt = np.linalg.svd(directions.T @ sphere_vertices)
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


def _normalised(points):
    """Centre on the bounding box and scale into [-1, 1]^3 (keeping proportions)."""
    low, high = points.min(axis=0), points.max(axis=0)
    return (points - (low + high) / 2) / max((high - low).max() / 2, 1e-300)


def _visible(triangles, eye):
    """Front-facing triangles (indices) in back-to-front order, and their unit normals."""
    normals = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    # A mesh wound inward (allowed as input) would show its back: judge by the enclosed volume.
    if np.einsum("ij,ij->i", triangles[:, 0], normals).sum() < 0:
        normals = -normals
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
    front = np.flatnonzero(normals @ eye > 0)
    depth = triangles[front].mean(axis=1) @ eye
    order = front[np.argsort(depth)]
    return order, normals


def _shade(colours, normals, eye):
    """Lambert shading: ambient plus diffuse light from above the camera's left shoulder."""
    light = eye + np.array([0.0, 0.0, 0.6]) + 0.4 * np.cross([0.0, 0.0, 1.0], eye)
    light /= np.linalg.norm(light)
    intensity = 0.45 + 0.55 * np.clip(normals @ light, 0, 1)
    shaded = np.array(colours, float, copy=True)
    shaded[:, :3] *= intensity[:, None]
    return shaded


def _draw(ax, triangles, colours, eye, edges=False):
    """Draw the visible triangles of one panel (coordinates already in [-1, 1]^3)."""
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    order, normals = _visible(triangles, eye)
    shaded = _shade(colours[order], normals[order], eye)
    # Without drawn edges, outline each triangle in its own colour: antialiasing would otherwise
    # leave light seams between neighbours.
    faces = Poly3DCollection(triangles[order], facecolors=shaded,
                             edgecolors=(0.1, 0.1, 0.1, 0.35) if edges else shaded, linewidths=0.3)
    ax.add_collection3d(faces)
    ax.set_xlim(-1, 1)
    ax.set_ylim(-1, 1)
    ax.set_zlim(-1, 1)
    ax.set_box_aspect((1, 1, 1), zoom=1.2)
    ax.view_init(elev=VIEW_ELEVATION, azim=VIEW_AZIMUTH)
    ax.set_axis_off()
    return len(order)


def checker_triangles(mesh_vertices, sphere_vertices, faces, levels):
    """Split each triangle into 4**levels and colour each piece by the checker of its sphere point.

    The sphere point of a piece is its centroid's barycentric blend of the triangle's three sphere
    positions, projected onto the sphere; its longitude and latitude pick the square.

    Returns
    -------
    triangles : (t * 4**levels, 3, 3) float array
        The pieces on the input mesh.
    checker_value : (t * 4**levels,) int array
        0 or 1.
    """
    from .texture import checker, longitude_latitude

    bary = np.array([[[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]]])
    for _ in range(levels):
        a, b, c = bary[:, 0], bary[:, 1], bary[:, 2]
        ab, bc, ca = (a + b) / 2, (b + c) / 2, (c + a) / 2
        bary = np.concatenate([np.stack(s, axis=1) for s in
                               ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
    M = mesh_vertices[faces]                                   # (t, 3, 3)
    S = sphere_vertices[faces]
    triangles = np.einsum("pkj,tjd->tpkd", bary, M).reshape(-1, 3, 3)
    centre = np.einsum("pj,tjd->tpd", bary.mean(axis=1), S).reshape(-1, 3)
    longitude, latitude = longitude_latitude(centre / np.linalg.norm(centre, axis=1, keepdims=True))
    uv = np.c_[longitude / (2 * np.pi) + 0.5, latitude / np.pi + 0.5]
    return triangles, checker(uv, CHECKER_SQUARES)


def render_png(path, mesh_vertices, sphere_vertices, faces, measure="area", title=None,
               max_faces=60000, dpi=100):
    """Write a PNG of the map: mesh and sphere coloured by distortion, and a checkerboarded mesh.

    Written atomically (a temporary file beside ``path``, renamed into place).

    Parameters
    ----------
    path : str or Path
    mesh_vertices : (n, 3) float array
        The input mesh.
    sphere_vertices : (n, 3) float array
        Its positions on the unit sphere.
    faces : (t, 3) int array
    measure : {"area", "angle"}
        Colouring of panels 1 and 2 (see :func:`triangle_measure`).
    title : str, optional
        A line above the panels.
    max_faces : int
        Panel 3 splits each triangle into 4, 16 or 64 pieces only while the total stays under this;
        it bounds the drawing time (an 86,000-triangle mesh draws in about 3 s).
    dpi : int

    Returns
    -------
    dict
        ``colour_limits`` of the measure and the number of triangles drawn per panel.

    Examples
    --------
    >>> import os, tempfile
    >>> from sphere_nlp.shapes import icosphere
    >>> V, F = icosphere(2)
    >>> with tempfile.TemporaryDirectory() as d:
    ...     info = render_png(os.path.join(d, "map.png"), V * [1, 1, 0.6], V, F)
    ...     open(os.path.join(d, "map.png"), "rb").read(8) == b"\\x89PNG\\r\\n\\x1a\\n"
    True
    """
    import matplotlib
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize
    from matplotlib.figure import Figure

    mesh_vertices = np.asarray(mesh_vertices, float)
    sphere_vertices = np.asarray(sphere_vertices, float)
    faces = np.asarray(faces, np.int64)
    label, colour_map_name = MEASURES.get(measure, (None, None))
    values = triangle_measure(mesh_vertices, sphere_vertices, faces, measure)
    finite = values[np.isfinite(values)]
    # Robust limits: the 98th percentile, so a few extreme slivers do not wash out the picture.
    spread = float(np.percentile(np.abs(finite), 98)) if len(finite) else 1.0
    spread = max(spread, 1e-3)
    norm = Normalize(-spread, spread) if measure == "area" else Normalize(0, spread)
    colour_map = matplotlib.colormaps[colour_map_name]
    colours = colour_map(norm(np.nan_to_num(values, nan=0.0)))

    eye = camera_direction()
    mesh = _normalised(mesh_vertices)
    sphere = sphere_vertices @ align_sphere_to_mesh(mesh_vertices, sphere_vertices).T
    edges = len(faces) <= 2000
    levels = 0
    while levels < 3 and len(faces) * 4 ** (levels + 1) <= max_faces:
        levels += 1
    pieces, checker_value = checker_triangles(mesh, sphere_vertices, faces, levels)
    checker_colours = np.c_[CHECKER_COLOURS[checker_value], np.ones(len(checker_value))]

    fig = Figure(figsize=(15, 5.6), dpi=dpi)
    FigureCanvasAgg(fig)
    drawn = []
    captions = ("mesh, coloured by %s" % label.split(" (")[0], "sphere, same colours",
                "mesh with a longitude/latitude checkerboard")
    panels = ((mesh[faces], colours, edges), (sphere[faces], colours, edges),
              (pieces, checker_colours, False))
    for k, (triangles, panel_colours, panel_edges) in enumerate(panels):
        # Fixed boxes and captions under each: 3D axes place their titles unreliably.
        ax = fig.add_axes((k / 3, 0.19, 1 / 3, 0.74), projection="3d")
        drawn.append(_draw(ax, triangles, panel_colours, eye, panel_edges))
        fig.text(k / 3 + 1 / 6, 0.17, captions[k], ha="center", fontsize=12)
    bar_axes = fig.add_axes((0.12, 0.085, 0.42, 0.025))
    bar = fig.colorbar(ScalarMappable(norm=norm, cmap=colour_map), cax=bar_axes, orientation="horizontal",
                       extend="both" if measure == "area" else "max")
    bar.set_label(label, fontsize=11)
    if title:
        fig.text(0.5, 0.95, title, ha="center", fontsize=13)
    with atomic_output(path, "wb") as out:
        fig.savefig(out, format="png")
    return {"colour_limits": (float(norm.vmin), float(norm.vmax)), "drawn_triangles": drawn,
            "checker_levels": levels}
