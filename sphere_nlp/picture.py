"""A picture of a spherical map: mesh and sphere coloured by distortion, and the mesh checkerboarded.

:func:`render_png` draws three panels side by side, offscreen (matplotlib's Agg backend, no display
needed):

1. the input mesh, each triangle coloured by a distortion measure of the map
   (:func:`sphere_nlp.metrics.area_log_ratio` or :func:`sphere_nlp.metrics.angle_distortion`);
2. the sphere, coloured the same way, turned to show the same side as panel 1;
3. the input mesh textured with a checkerboard in the sphere's longitude and latitude, the (u, v) of
   :mod:`sphere_nlp.texture`: squares that stay square mean angles are kept, equal sizes mean areas are.

Choices that make the picture say something:

* **Upright.** Meshes come Y-up (most graphics meshes: Stanford scans, OBJ exports) or Z-up (CAD,
  scans of busts, medical data), and the picture draws the mesh's up axis up. Unless given
  (``up="y"``, ``"-z"``, a vector), :func:`detect_up` finds it: the axis pointing away from a flat
  base (a bust's cut, a pedestal, a cylinder's cap) when there is one, else away from the feet of
  three or more legs (an animal, whichever axis it was modelled along), else +Y.
* **View.** Unless one is given, the camera looks from the direction, level or from above, in which
  the upright mesh shows the most projected area (:func:`best_view`), so a model is seen from its
  broad side, not end-on.
* **Colour scale.** Labelled ticks that name its range: from 0 for the angle distortion; for the
  signed log area ratio white at 0 (a triangle keeping its share of the surface), symmetric unless
  one side reaches less than half as far as the other, then each side on its own linear scale (a
  default-mode map shrinks limbs by e^-15 and grows the body by e^1: on a +-15 scale the sphere,
  all body, would be white). The scale reaches the 2nd and 98th percentiles of what the panels
  show (mesh and sphere areas), rounded up to a tick (:func:`colour_range`); the share of the
  surface beyond it is stated under the colour bar, so a few extreme slivers cannot wash the
  picture out.
* **Checkerboard.** The colours of the texture written beside OBJ files
  (:data:`sphere_nlp.texture.CHECKER_COLOURS`), so the picture shows what a viewer shows. Each
  triangle is cut exactly along the checker lines in its (u, v) (linear in the triangle, as a
  viewer's texture lookup is), so square edges are straight, not staircases.

Triangles are drawn flat with Lambert shading; those facing away from the camera are culled and the
rest depth-sorted by mplot3d (painter's algorithm), exact for the sphere and good for most meshes.
"""

import numpy as np

from .geometry import rotation_between
from .mesh_io import atomic_output
from .texture import CHECKER_COLOURS as TEXTURE_CHECKER_COLOURS

# The camera (degrees) when a view is neither given nor chosen: a little from above, as in Fig. 3.
VIEW_ELEVATION, VIEW_AZIMUTH = 20.0, -60.0
CHECKER_SQUARES = (16, 8)            # along longitude, along latitude: 22.5-degree squares
CHECKER_COLOURS = np.asarray(TEXTURE_CHECKER_COLOURS, float) / 255     # those of the written texture
MEASURES = {
    "area": ("log(sphere area / mesh area)", "RdBu_r"),
    "angle": ("angle distortion (degrees)", "viridis"),
}
COLOUR_PERCENTILES = (2.0, 98.0)     # area-weighted; the rest is clipped and its share stated
UP_AXES = ("+x", "+y", "+z", "-x", "-y", "-z")     # detect_up's answers, in its order of preference
FLAT_BASE_SHARE = 0.02               # a flat base holds at least this share of the surface ...
FLAT_BASE_BAND = 0.005               # ... within this fraction of the mesh's size of its lowest point
FLAT_BASE_COS = np.cos(np.radians(5.0))      # ... facing within 5 degrees of straight down
# Legs are looked for in the lowest 10% of the height: there a standing animal's legs are separate
# columns (cat, koala, spot), while at a quarter of the height a cow's belly already joins them.
LEG_SLAB = 0.1
LEG_REACH = 0.2                      # a leg reaches within this share of the slab of its floor and top


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


def up_vector(up):
    """The unit vector of an up axis: ``"x"``, ``"+y"``, ``"-z"``, ... or any nonzero 3-vector.

    >>> up_vector("y").tolist(), up_vector("-z").tolist()
    ([0.0, 1.0, 0.0], [0.0, 0.0, -1.0])
    """
    if isinstance(up, str):
        text = up.strip().lower()
        sign, axis = (-1.0 if text[:1] == "-" else 1.0), text.lstrip("+-")
        if axis not in ("x", "y", "z") or len(text) - len(axis) > 1:
            raise ValueError("up must be x, y, z, -x, -y, -z or a vector, got %r" % up)
        vector = np.zeros(3)
        vector["xyz".index(axis)] = sign
        return vector
    vector = np.asarray(up, float).reshape(-1)
    if vector.shape != (3,) or not np.isfinite(vector).all() or np.linalg.norm(vector) == 0:
        raise ValueError("up must be x, y, z, -x, -y, -z or a nonzero 3-vector, got %r" % (up,))
    return vector / np.linalg.norm(vector)


def flat_base_shares(vertices, faces):
    """Per direction of :data:`UP_AXES`: the share of the surface lying flat at the mesh's bottom if
    that direction were up, (6,).

    A triangle counts when its centre is within 0.5% of the mesh's size of the lowest point and it
    faces within 5 degrees of straight down (normals judged outward by the enclosed volume): a plane
    cut, not the gently curved side of a long smooth shape.
    """
    vertices, faces = np.asarray(vertices, float), np.asarray(faces, np.int64)
    triangles = vertices[faces]
    normals = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    areas = np.linalg.norm(normals, axis=1) / 2
    normals /= np.maximum(2 * areas, 1e-300)[:, None]
    centres = triangles.mean(axis=1)
    if np.einsum("ij,ij,i->", centres - vertices.mean(axis=0), normals, areas) < 0:
        normals = -normals                                # wound inward
    size = max(np.ptp(vertices, axis=0).max(), 1e-300)
    shares = []
    for axis in UP_AXES:
        up = up_vector(axis)
        base = ((centres @ up < (vertices @ up).min() + FLAT_BASE_BAND * size)
                & (normals @ up < -FLAT_BASE_COS))
        shares.append(areas[base].sum() / max(areas.sum(), 1e-300))
    return np.array(shares)


def standing_legs(vertices, faces):
    """Per direction of :data:`UP_AXES`: how many legs the mesh would stand on if that direction
    were up, (6,) ints (0 when it would not stand).

    A leg is a separate piece of the surface in the lowest 10% of the height that crosses that slab,
    from near the floor to near its top (a column, not a bump of a back lying on the floor). The
    mesh stands when at least three legs hold its area centroid above the polygon of their feet.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    vertices, faces = np.asarray(vertices, float), np.asarray(faces, np.int64)
    triangles = vertices[faces]
    areas = np.linalg.norm(np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0]), axis=1)
    centroid = (triangles.mean(axis=1) * areas[:, None]).sum(axis=0) / max(areas.sum(), 1e-300)
    edges = np.r_[faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]
    legs = []
    for axis in UP_AXES:
        up = up_vector(axis)
        height = vertices @ up
        floor = height.min()
        slab = LEG_SLAB * max(np.ptp(height), 1e-300)
        low = height < floor + slab
        kept = edges[(low[faces].all(axis=1))[np.arange(len(edges)) % len(faces)]]
        graph = coo_matrix((np.ones(len(kept)), (kept[:, 0], kept[:, 1])), shape=(len(vertices),) * 2)
        _, labels = connected_components(graph, directed=False)
        in_slab = np.zeros(len(vertices), bool)
        in_slab[kept.ravel()] = True
        pieces = labels[in_slab]
        lowest = np.full(labels.max() + 1, np.inf)
        highest = np.full(labels.max() + 1, -np.inf)
        np.minimum.at(lowest, pieces, height[in_slab])
        np.maximum.at(highest, pieces, height[in_slab])
        columns = np.flatnonzero((lowest < floor + LEG_REACH * slab) & (highest > floor + (1 - LEG_REACH) * slab))
        feet = np.array([vertices[in_slab][pieces == c].mean(axis=0) for c in columns]).reshape(-1, 3)
        basis = np.linalg.svd(np.eye(3) - np.outer(up, up))[0][:, :2]
        standing = len(columns) >= 3 and _inside_hull(feet @ basis, centroid @ basis)
        legs.append(len(columns) if standing else 0)
    return np.array(legs)


def _inside_hull(points, point):
    """Whether ``point`` lies inside the convex hull of the 2D ``points`` (False when they are collinear)."""
    from scipy.spatial import ConvexHull, QhullError

    try:
        hull = ConvexHull(points)
    except (QhullError, ValueError):
        return False
    return bool((hull.equations[:, :2] @ point + hull.equations[:, 2] <= 1e-12).all())


def detect_up(vertices, faces):
    """The mesh's up axis, one of :data:`UP_AXES`.

    A mesh with a flat base (a bust's cut, a pedestal, a cylinder's cap: at least 2% of the surface
    flat at the bottom, :func:`flat_base_shares`) stands on it; of several within 10% of the largest,
    the first in :data:`UP_AXES` (+Y before +Z, + before -). Else an animal stands on its legs: the
    direction in which the most legs (at least three) hold it up (:func:`standing_legs`), first in
    :data:`UP_AXES` on a tie, so a cat or a koala modelled Z-up, or lying along any axis, is drawn
    standing. Else +Y: the convention of most graphics meshes (the Stanford bunny and armadillo,
    meshes exported as OBJ); two-legged figures are left to it, since a figure lying on its back
    has two columns (its heels) as well. Z-up meshes without a flat base or legs (FreeSurfer's
    cortical surfaces, in RAS coordinates) need ``up="z"``.

    Examples
    --------
    >>> from sphere_nlp.shapes import cylinder, icosphere
    >>> detect_up(*cylinder())                    # flat caps at -z and +z
    '+z'
    >>> V, F = icosphere(3)
    >>> detect_up(V * [1, 2, 1], F)                # no flat base: the Y-up convention
    '+y'
    """
    shares = flat_base_shares(vertices, faces)
    if shares.max() >= FLAT_BASE_SHARE:
        return UP_AXES[int(np.flatnonzero(shares >= 0.9 * shares.max())[0])]
    legs = standing_legs(vertices, faces)
    if legs.max() >= 3:
        return UP_AXES[int(np.argmax(legs))]
    return "+y"


def upright_rotation(up):
    """The rotation R (3, 3) turning ``up`` to +Z by the smallest angle (Rodrigues): for +Y up, the
    mesh's front (+Z, the graphics convention) then faces -Y, the default camera's side.

    >>> R = upright_rotation("y")
    >>> (R @ [0, 1, 0]).round(12).tolist(), (R @ [0, 0, 1]).round(12).tolist()
    ([0.0, 0.0, 1.0], [0.0, -1.0, 0.0])
    """
    return rotation_between(up_vector(up), np.array([0.0, 0.0, 1.0]))


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


def _draw(ax, triangles, colours, view, edges=False, pieces=None):
    """Draw the visible triangles of one panel (coordinates already in [-1, 1]^3).

    ``pieces`` = (polygons, parent) draws polygons cut from the triangles instead, each shaded and
    culled as its parent triangle; ``colours`` are then the pieces'.
    """
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    azimuth, elevation = view
    eye = camera_direction(elevation, azimuth)
    order, normals = _visible(triangles, eye)
    if pieces is None:
        polygons, shaded = triangles[order], _shade(colours[order], normals[order], eye)
    else:
        polygons, parent = pieces
        shown = np.zeros(len(triangles), bool)
        shown[order] = True
        keep = np.flatnonzero(shown[parent])
        # Pad each piece to the longest by repeating its last corner: for ragged polygons mplot3d
        # pads with uninitialised memory and autoscales over it, which can raise on inf limits.
        longest = max((len(polygons[i]) for i in keep), default=3)
        padded = np.empty((len(keep), longest, 3))
        for row, i in enumerate(keep):
            padded[row] = polygons[i][np.minimum(np.arange(longest), len(polygons[i]) - 1)]
        polygons = padded
        shaded = _shade(colours[keep], normals[parent[keep]], eye)
    # Without drawn edges, outline each polygon in its own colour: antialiasing would otherwise
    # leave light seams between neighbours.
    faces = Poly3DCollection(polygons, facecolors=shaded,
                             edgecolors=(0.1, 0.1, 0.1, 0.35) if edges else shaded, linewidths=0.3)
    ax.add_collection3d(faces)
    ax.set_xlim(-1, 1)
    ax.set_ylim(-1, 1)
    ax.set_zlim(-1, 1)
    ax.set_box_aspect((1, 1, 1), zoom=1.2)
    ax.view_init(elev=elevation, azim=azimuth)
    ax.set_axis_off()
    return len(polygons)


def best_view(vertices, faces, step=15.0):
    """(azimuth, elevation) in degrees from which the mesh (Z up) shows the most projected area.

    Scores every direction of a 15-degree grid, level to 60 degrees above, by the area of the
    front-facing triangles projected onto the image plane (for a convex shape, its silhouette's
    area), and prefers, by up to 3%, views near the default (from a little above, front left).

    Examples
    --------
    >>> from sphere_nlp.shapes import icosphere
    >>> V, F = icosphere(2)
    >>> best_view(V * [1, 0.2, 1], F)[0] in (-90.0, 90.0)     # a flat plate is seen face-on
    True
    """
    vertices, faces = np.asarray(vertices, float), np.asarray(faces, np.int64)
    triangles = vertices[faces]
    area_vectors = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0]) / 2
    if np.einsum("ij,ij->i", triangles[:, 0] - vertices.mean(axis=0), area_vectors).sum() < 0:
        area_vectors = -area_vectors                      # wound inward: outward normals all the same
    elevations = np.arange(0.0, 60.0 + 1e-9, step)
    azimuths = np.arange(-180.0, 180.0, step)
    views = np.array([(el, az) for el in elevations for az in azimuths])
    directions = np.array([camera_direction(el, az) for el, az in views])       # (k, 3)
    projected = np.clip(area_vectors @ directions.T, 0, None).sum(axis=0)
    preference = 1 + 0.03 * (directions @ camera_direction() + 1) / 2
    el, az = views[int(np.argmax(projected * preference))]
    return float(az), float(el)


def weighted_percentile(values, weights, q):
    """Percentile ``q`` (0-100) of ``values`` where each counts with its weight: the smallest value
    with at least ``q`` percent of the weight at or below it.

    Examples
    --------
    >>> float(weighted_percentile([0.0, 1.0, 2.0], [1.0, 1.0, 2.0], 50))
    1.0
    >>> float(weighted_percentile([0.0, 10.0], [99.0, 1.0], 98))
    0.0
    """
    values, weights = np.asarray(values, float), np.asarray(weights, float)
    order = np.argsort(values)
    values, weights = values[order], weights[order]
    cumulative = np.cumsum(weights)
    if cumulative[-1] <= 0:
        return float(np.percentile(values, q))
    index = np.searchsorted(cumulative / cumulative[-1], q / 100 - 1e-12)
    return float(values[min(index, len(values) - 1)])


def tick_step(extent, per_side=3):
    """The smallest round step (1, 2, 2.5 or 5 times a power of ten) dividing ``extent`` into at
    most ``per_side`` steps.

    >>> tick_step(0.47), tick_step(14.0), tick_step(3.0)
    (0.2, 5.0, 1.0)
    """
    raw = max(float(extent), 1e-12) / per_side
    power = 10.0 ** np.floor(np.log10(raw))
    step = next(m * power for m in (1, 2, 2.5, 5, 10) if m * power >= raw * (1 - 1e-9))
    return float(np.round(step, 12))


def _side(reach):
    """(end, ticks from 0 out) of one side of a colour scale reaching ``reach`` >= 0: the reach
    rounded up to a round step (:func:`tick_step`), two or three steps from 0."""
    step = tick_step(reach)
    steps = int(np.ceil(reach / step - 1e-9))
    return float(np.round(steps * step, 12)), [float(np.round(k * step, 12)) for k in range(1, steps + 1)]


def colour_range(values, weights, measure, shown=None):
    """(low, high, ticks, clipped share): the colour scale of a measure.

    The scale reaches the weighted 2nd and 98th percentiles, each rounded up to a round tick step
    (:func:`tick_step`). The angle distortion's starts at 0. The signed log area ratio's has 0
    (white: a triangle keeping its share of the surface) in its middle and is symmetric (equal
    colours, equal factors of growth and shrinkage) unless one side reaches less than half as far as
    the other: then each side has its own range, so a default-mode map whose limbs shrink by e^-15
    while its body grows by e^1 shows the body in red instead of washing it out on a +-15 scale;
    the colour bar's ticks name both ends. Neither side reaches less than a tenth of the other.
    The percentiles are taken with the ``shown`` weights (by default ``weights``: give what both
    panels show, the mesh's and the sphere's areas, so neither panel is left blank); the clipped
    share is that of ``weights`` beyond the scale. ``ticks`` are evenly spaced on each side, 0 among them.

    Examples
    --------
    >>> v = np.r_[np.linspace(-1, 1, 98), 50.0, -50.0]
    >>> low, high, ticks, share = colour_range(v, np.ones(100), "area")
    >>> low, high, ticks, share
    (-1.0, 1.0, [-1.0, -0.5, 0.0, 0.5, 1.0], 0.02)
    >>> colour_range(np.linspace(-14, 1.2, 100), np.ones(100), "area")[:3]      # two-sided
    (-15.0, 1.5, [-15.0, -10.0, -5.0, 0.0, 0.5, 1.0, 1.5])
    >>> colour_range(np.r_[np.zeros(50), np.full(50, 4.0)], np.ones(100), "angle")[:3]
    (0.0, 4.0, [0.0, 2.0, 4.0])
    """
    values, weights = np.asarray(values, float), np.asarray(weights, float)
    shown = weights if shown is None else np.asarray(shown, float)
    finite = np.isfinite(values)
    if finite.any():
        quantiles = [weighted_percentile(values[finite], shown[finite], q) for q in COLOUR_PERCENTILES]
    else:
        quantiles = [0.0, 0.0]
    if measure == "area":
        below, above = max(-quantiles[0], 1e-3), max(quantiles[1], 1e-3)
        larger = max(below, above)
        if min(below, above) >= larger / 2:
            below = above = larger
        below, above = max(below, larger / 10), max(above, larger / 10)
        low, low_ticks = _side(below)
        high, high_ticks = _side(above)
        low, ticks = -low, [-t for t in low_ticks[::-1]] + [0.0] + high_ticks
    else:
        high, high_ticks = _side(max(quantiles[1], 1e-3))
        low, ticks = 0.0, [0.0] + high_ticks
    beyond = weights[finite][(values[finite] < low) | (values[finite] > high)].sum()
    return low, high, ticks, float(beyond / max(weights.sum(), 1e-300))


def _split(polygon, axis, cut):
    """The parts of a convex polygon (rows u, v, x, y, z, linear in each other) below and above
    ``row[axis] = cut`` (Sutherland-Hodgman)."""
    side = polygon[:, axis] - cut
    below, above = [], []
    for k in range(len(polygon)):
        p, q, sp, sq = polygon[k], polygon[(k + 1) % len(polygon)], side[k], side[(k + 1) % len(polygon)]
        (below if sp <= 0 else above).append(p)
        if (sp < 0 < sq) or (sq < 0 < sp):
            crossing = p + (q - p) * (sp / (sp - sq))
            below.append(crossing)
            above.append(crossing)
    return [np.array(part) for part in (below, above) if len(part) >= 3]


def checker_pieces(positions, faces, corner_uv, squares=CHECKER_SQUARES):
    """Cut each triangle along the checker lines of its (u, v) (linear in the triangle, as a texture
    lookup is) and give each piece its square's value.

    Returns
    -------
    polygons : list of (k, 3) arrays
        The pieces on ``positions``; a triangle inside one square stays whole.
    value : (m,) int array
        0 or 1 per piece, as :func:`sphere_nlp.texture.checker`.
    parent : (m,) int array
        The triangle each piece comes from.

    Examples
    --------
    >>> V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    >>> uv = np.array([[[0.01, 0.01], [0.1, 0.01], [0.01, 0.1]]])
    >>> polygons, value, parent = checker_pieces(V, np.array([[0, 1, 2]]), uv)
    >>> len(polygons), value.tolist()                  # the checker line u = 1/16 cuts it in two
    (2, [0, 1])
    """
    from .texture import checker

    positions, faces = np.asarray(positions, float), np.asarray(faces, np.int64)
    corner_uv = np.asarray(corner_uv, float)
    scale = np.asarray(squares, float)
    cell = np.floor(corner_uv * scale).astype(np.int64)              # (t, 3, 2)
    whole = (cell == cell[:, :1]).all(axis=(1, 2))
    polygons = list(positions[faces[whole]])
    value = list(checker(corner_uv[whole].mean(axis=1), squares))
    parent = list(np.flatnonzero(whole))
    for t in np.flatnonzero(~whole):
        pieces = [np.c_[corner_uv[t], positions[faces[t]]]]
        for axis in (0, 1):
            lines = np.arange(cell[t, :, axis].min() + 1, cell[t, :, axis].max() + 1) / scale[axis]
            for cut in lines:
                pieces = [part for piece in pieces for part in _split(piece, axis, cut)]
        for piece in pieces:
            polygons.append(piece[:, 2:])
            value.append(int(checker(piece[:, :2].mean(axis=0), squares)))
            parent.append(t)
    return polygons, np.asarray(value, np.int64), np.asarray(parent, np.int64)


def default_measure(target):
    """The measure a picture shows by default: what the mode does *not* optimise (its cost).

    >>> default_measure("original-areas"), default_measure("original-angles")
    ('angle', 'area')
    """
    return "angle" if str(target).endswith("areas") else "area"


def render_png(path, mesh_vertices, sphere_vertices, faces, measure="area", title=None,
               view=None, corner_uv=None, dpi=100, up=None):
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
    view : (azimuth, elevation) in degrees, optional
        The camera, around the upright mesh (elevation 90 looks down on it); by default
        :func:`best_view` of the upright mesh.
    corner_uv : (t, 3, 2) float array, optional
        Texture coordinates of the checkerboard; by default
        :func:`sphere_nlp.texture.spherical_uv` of the sphere, as in the OBJ.
    dpi : int
    up : str or (3,) array, optional
        The mesh's up axis, drawn up: ``"y"``, ``"-z"``, ... or a vector (:func:`up_vector`); by
        default :func:`detect_up`.

    Returns
    -------
    dict
        ``colour_limits``, ``colour_ticks``, ``clipped_share`` (of the surface beyond the limits),
        ``up`` (as given or detected), ``view``, the number of polygons drawn per panel (``drawn``)
        and ``checker_pieces``.

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
    from matplotlib.colors import Normalize, TwoSlopeNorm
    from matplotlib.figure import Figure

    from .metrics import normalised_areas_3d
    from .texture import spherical_uv

    mesh_vertices = np.asarray(mesh_vertices, float)
    sphere_vertices = np.asarray(sphere_vertices, float)
    faces = np.asarray(faces, np.int64)
    if measure not in MEASURES:
        raise ValueError("measure must be one of %s, got %r" % (", ".join(MEASURES), measure))
    if view is not None:
        view = tuple(float(a) for a in view)
        # A NaN or infinite camera draws every panel blank.
        if len(view) != 2 or not np.isfinite(view).all() or not -90 <= view[1] <= 90:
            raise ValueError("view must be (azimuth, elevation): finite degrees, the elevation in "
                             "[-90, 90]; got %r" % (view,))
    label, colour_map_name = MEASURES[measure]
    values = triangle_measure(mesh_vertices, sphere_vertices, faces, measure)
    mesh_share = normalised_areas_3d(mesh_vertices, faces)
    # What the two panels show: each triangle with its mesh share and its sphere share (the mesh's
    # times the area ratio), so that the body filling a default-mode map's sphere gets colours.
    sphere_share = mesh_share * np.exp(np.clip(np.nan_to_num(values, nan=0.0, neginf=-700.0), -700, 700)) \
        if measure == "area" else mesh_share
    low, high, ticks, clipped = colour_range(values, mesh_share, measure,
                                             shown=mesh_share / mesh_share.sum() + sphere_share / sphere_share.sum())
    norm = TwoSlopeNorm(0.0, low, high) if measure == "area" else Normalize(low, high)
    colour_map = matplotlib.colormaps[colour_map_name]
    colours = colour_map(norm(np.nan_to_num(values, nan=0.0)))

    detected = up is None
    up = detect_up(mesh_vertices, faces) if detected else up
    up_text = up if isinstance(up, str) else "(%.2g, %.2g, %.2g)" % tuple(up_vector(up))
    upright = upright_rotation(up)
    mesh = _normalised(mesh_vertices @ upright.T)
    view = view if view is not None else best_view(mesh, faces)
    sphere = sphere_vertices @ (upright @ align_sphere_to_mesh(mesh_vertices, sphere_vertices)).T
    edges = len(faces) <= 2000
    if corner_uv is None:
        corner_uv = spherical_uv(sphere_vertices, faces)
    polygons, checker_value, parent = checker_pieces(mesh, faces, corner_uv)
    checker_colours = np.c_[CHECKER_COLOURS[checker_value], np.ones(len(checker_value))]

    fig = Figure(figsize=(15, 5.6), dpi=dpi)
    FigureCanvasAgg(fig)
    drawn = []
    captions = ("mesh, coloured by %s" % label.split(" (")[0], "sphere, same colours",
                "mesh with a longitude/latitude checkerboard")
    panels = ((mesh[faces], colours, edges, None), (sphere[faces], colours, edges, None),
              (mesh[faces], checker_colours, False, (polygons, parent)))
    for k, (triangles, panel_colours, panel_edges, pieces) in enumerate(panels):
        # Fixed boxes and captions under each: 3D axes place their titles unreliably.
        ax = fig.add_axes((k / 3, 0.19, 1 / 3, 0.74), projection="3d")
        drawn.append(_draw(ax, triangles, panel_colours, view, panel_edges, pieces))
        fig.text(k / 3 + 1 / 6, 0.17, captions[k], ha="center", fontsize=12)
    bar_axes = fig.add_axes((0.12, 0.085, 0.42, 0.025))
    bar = fig.colorbar(ScalarMappable(norm=norm, cmap=colour_map), cax=bar_axes, orientation="horizontal",
                       extend="both" if measure == "area" else "max")
    bar.set_ticks(ticks)
    bar.ax.xaxis.set_major_formatter("{x:g}")
    two_sided = measure == "area" and low != -high
    bar.set_label("%s from %g to %g%s; %.1f%% of the surface beyond the range"
                  % (label, low, high, " (each side of 0 on its own scale)" if two_sided else "", 100 * clipped),
                  fontsize=11)
    fig.text(0.56, 0.085, "up: %s%s; view: azimuth %g°, elevation %g°"
             % ((up_text, " (detected)" if detected else "") + view), fontsize=10)
    if title:
        fig.text(0.5, 0.95, title, ha="center", fontsize=13)
    with atomic_output(path, "wb") as out:
        fig.savefig(out, format="png")
    return {"colour_limits": (low, high), "colour_ticks": ticks, "clipped_share": clipped,
            "up": up_text, "view": view, "drawn": drawn, "checker_pieces": len(polygons)}


# A map whose triangles are on average within this |log area ratio| of their share of the sphere
# keeps the areas (an area mode's map: about 0.01-0.03), so its picture shows the angles it pays.
AREA_KEPT_MEAN_ABS_LOG = 0.05


def measure_for_map(mesh_vertices, sphere_vertices, faces):
    """The measure a picture of a map of unknown mode shows: "angle" when the map keeps the areas
    (mean |log area ratio| below :data:`AREA_KEPT_MEAN_ABS_LOG`), else "area" (what a map in an
    angle mode pays), as :func:`default_measure` chooses from a mode.

    >>> from sphere_nlp.shapes import icosphere
    >>> V, F = icosphere(2)
    >>> measure_for_map(V, V, F), measure_for_map(V * [1, 1, 3], V, F)
    ('angle', 'area')
    """
    from .metrics import area_log_ratio, normalised_areas_3d

    log_area = area_log_ratio(mesh_vertices, sphere_vertices, faces)
    weights = normalised_areas_3d(mesh_vertices, faces)
    finite = np.isfinite(log_area)
    mean = (np.abs(log_area[finite]) * weights[finite]).sum() / max(weights[finite].sum(), 1e-300)
    return "angle" if mean < AREA_KEPT_MEAN_ABS_LOG else "area"


def picture_name(sphere_path):
    """Where a picture of the map in ``sphere_path`` goes by default: beside it, named after it
    without ``.sphere`` and its extension (``out/bunny.sphere.off`` -> ``out/bunny.png``,
    ``bunny.original-areas.sphere.off`` -> ``bunny.original-areas.png``, ``cyl.obj`` -> ``cyl.png``),
    so a picture carries the mode its sphere's name carries.

    >>> str(picture_name("out/bunny.original-areas.sphere.off")), str(picture_name("cyl.obj"))
    ('out/bunny.original-areas.png', 'cyl.png')
    """
    from pathlib import Path

    path = Path(sphere_path)
    stem = path.stem[:-len(".sphere")] if path.stem.endswith(".sphere") else path.stem
    return path.with_name((stem or path.stem) + ".png")


def main(argv=None):
    """``sphere-nlp picture MESH SPHERE [-o OUT.png]``: redraw a map written earlier, without solving."""
    import sys
    from pathlib import Path

    from .commands import (UP_CHOICES, check_output_paths, join_negative_values, run_subcommand,
                           subcommand_parser, view_argument)
    from .errors import UsageError

    parser = subcommand_parser(
        "picture",
        description="Draw the picture of a map written earlier (MESH and its SPHERE, same faces), without "
                    "solving: mesh and sphere coloured by distortion, and the mesh checkerboarded.",
        epilog="example:\n  sphere-nlp bunny.off\n  sphere-nlp picture bunny.off bunny.sphere.off --up y "
               "--view -60,20")
    parser.add_argument("mesh", metavar="MESH", help="the mesh that was mapped")
    parser.add_argument("sphere", metavar="SPHERE",
                        help="its sphere (the main command's output, or any with the same vertices and faces; "
                             "any radius, centred at the origin)")
    parser.add_argument("-o", "--output", metavar="OUT.png",
                        help="the picture (default: beside SPHERE, named after it: bunny.sphere.off -> bunny.png)")
    parser.add_argument("--png-measure", "--measure", dest="measure", choices=tuple(MEASURES),
                        help="colouring: log area ratio or angle distortion (default: angle when the map keeps "
                             "the areas, else area)")
    parser.add_argument("--view", metavar="AZ,EL", type=view_argument,
                        help="camera azimuth and elevation, degrees (default: the side with the most projected area)")
    parser.add_argument("--up", choices=UP_CHOICES, metavar="AXIS",
                        help="the mesh's up axis: x, y, z, or --up=-z (default: detected)")
    parser.add_argument("-q", "--quiet", action="store_true", help="print only errors")

    def check(args):
        from .resample import _check_inputs, checked_sphere

        option = "-o" if args.output else "the default output"
        args.output = Path(args.output) if args.output else picture_name(args.sphere)
        _check_inputs(args.mesh, args.sphere)
        check_output_paths([("the input mesh", args.mesh), ("the sphere", args.sphere)],
                           [(option, args.output)])
        if args.output.suffix.lower() != ".png":
            raise UsageError("cannot write %s: a picture must end in .png" % args.output)
        # The sphere is read, matched to the mesh and certified before anything is drawn.
        args.map, args.note = checked_sphere(args.mesh, args.sphere)

    def body(args, say):
        from .mesh_io import output_transaction
        from .metrics import distortion_summary

        if args.note:
            say(args.note)
        X, S, F = args.map
        X = _normalised(X)
        measure = args.measure or measure_for_map(X, S, F)
        summary = distortion_summary(X, S, F)
        title = ("%s: %d vertices, mean angle distortion %.1f°, mean |log area ratio| %.3f"
                 % (Path(args.sphere).name, len(S), summary["mean_abs_angle_diff_deg"], summary["mean_abs_log_area"]))
        with output_transaction():
            info = render_png(args.output, X, S, F, measure=measure, title=title, view=args.view, up=args.up)
        low, high = info["colour_limits"]
        say("wrote %s: coloured by %s from %g to %g; up %s%s, view azimuth %g°, elevation %g°"
            % (args.output, MEASURES[measure][0], low, high, info["up"], " (detected)" if args.up is None else "",
               *info["view"]))
        return 0

    return run_subcommand(parser, join_negative_values(list(sys.argv[1:] if argv is None else argv)), body,
                          check=check, interrupted="nothing written", failed="nothing written")
