"""Texture coordinates from a spherical map: longitude and latitude of the sphere positions, per corner.

Convention (equirectangular, the layout of world maps and HDR environment maps)::

    u = longitude / (2 pi) + 0.5      longitude = atan2(y, x), in [-pi, pi]
    v = latitude / pi + 0.5           latitude = atan2(z, hypot(x, y)), in [-pi/2, pi/2]

so u runs eastward around the z axis from the -x direction (u = 0 and u = 1 are the seam, the
half-plane y = 0, x < 0) and v runs from the south pole (v = 0) to the north pole (v = 1). Seen from
outside the sphere, (u, v) keeps the orientation of counter-clockwise triangles.

Coordinates are given per *corner*, not per vertex, because two kinds of vertex need different (u, v)
in different triangles:

* **The seam.** A triangle that straddles u = 0 / u = 1 would stretch backwards across the whole
  texture. Its corners with u < 0.5 are shifted by +1 instead, so it stays narrow: such u exceed 1.
  Textures repeat (OBJ viewers and game engines wrap u by default), so u = 1.2 samples the same texel
  as u = 0.2. All u lie in [0, 2).
* **The poles.** A vertex at a pole has no longitude; a triangle with a pole inside it covers every
  longitude; a vertex very close to a pole can have a longitude that turns its uv triangle over. In
  each such triangle the corner nearest the pole gets the mean u of the other two (as if it were at the
  pole), and those two are unwrapped in the direction the triangle turns around the pole.

The result: every uv triangle of a certified map is counter-clockwise (positive area), so none is
mirrored or wraps around the texture, and together they cover the unit square about once.
"""

import numpy as np

# A vertex this close to the polar axis (relative to the unit sphere) has no usable longitude.
POLE_TOLERANCE = 1e-12


def longitude_latitude(points):
    """Longitude in [-pi, pi] and latitude in [-pi/2, pi/2] of points on (or near) the unit sphere.

    ``atan2`` for both, not ``arcsin(z)``: it keeps full accuracy near the poles.

    Examples
    --------
    >>> lon, lat = longitude_latitude(np.array([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0]]))
    >>> float(np.degrees(lon[0])), float(np.degrees(lat[1]))
    (90.0, -90.0)
    """
    points = np.asarray(points, float)
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    return np.arctan2(y, x), np.arctan2(z, np.hypot(x, y))


def spherical_uv(sphere_vertices, faces):
    """Per-corner texture coordinates (u, v) from the longitude and latitude of the sphere positions.

    Parameters
    ----------
    sphere_vertices : (n, 3) float array
        Positions on the unit sphere (the output of :func:`sphere_nlp.parameterize`).
    faces : (t, 3) int array
        Triangles, counter-clockwise seen from outside the sphere (as in a certified map).

    Returns
    -------
    corner_uv : (t, 3, 2) float array
        ``corner_uv[i, j]`` is (u, v) at vertex ``faces[i, j]`` in triangle ``i``; v in [0, 1],
        u in [0, 2) (seam-shifted corners exceed 1; see the module docstring). Every uv triangle of a
        certified map is counter-clockwise (positive area): none wraps around the texture.

    Examples
    --------
    >>> from sphere_nlp.shapes import octahedron
    >>> V, F = octahedron()
    >>> uv = spherical_uv(V, F)
    >>> uv.shape, float(uv[..., 1].min()), float(uv[..., 1].max())
    ((8, 3, 2), 0.0, 1.0)
    >>> bool((uv_signed_areas(uv) > 0).all())     # no triangle flipped or wrapped around the seam
    True
    """
    sphere_vertices = np.asarray(sphere_vertices, float)
    faces = np.asarray(faces, np.int64)
    longitude, latitude = longitude_latitude(sphere_vertices)
    u = longitude / (2 * np.pi) + 0.5
    v = latitude / np.pi + 0.5
    at_pole = np.hypot(sphere_vertices[:, 0], sphere_vertices[:, 1]) <= POLE_TOLERANCE
    corner_u = u[faces]
    corner_v = v[faces]
    # Seam: a triangle spanning more than half the longitudes goes the short way round instead.
    # (Pole corners have an arbitrary longitude; they are redone below.)
    masked = np.where(at_pole[faces], np.nan, corner_u)
    with np.errstate(all="ignore"):
        span = np.nanmax(masked, axis=1) - np.nanmin(masked, axis=1)
    wraps = span > 0.5
    corner_u = np.where(wraps[:, None] & (corner_u < 0.5), corner_u + 1, corner_u)
    corner_uv = np.stack([corner_u, corner_v], axis=-1)

    # Near a pole longitude stops describing where a triangle lies: a corner at the pole has none,
    # a triangle around the pole covers all of them, and a corner very near it can sit at a longitude
    # that turns the uv triangle over. All three get the pole treatment.
    fix = at_pole[faces].any(axis=1) | (uv_signed_areas(corner_uv) <= 0)
    fix[pole_triangles(sphere_vertices, faces)] = True
    rows = np.flatnonzero(fix)
    if len(rows):
        corner_uv[rows] = _pole_corner_uv(u[faces[rows]], corner_v[rows])
    return corner_uv


def _pole_corner_uv(corner_u, corner_v):
    """uv of triangles whose corner nearest a pole is treated as if it were on it.

    The other two corners a, b (in face order after the pole corner c) keep their longitudes,
    unwrapped in the direction a counter-clockwise triangle turns around that pole (eastward around
    the north pole, westward around the south pole); c gets their mean u and keeps its v. The result
    is counter-clockwise: its signed area is (u_b - u_a)(v_c - (v_a + v_b) / 2) / 2 with both factors
    of the same sign.
    """
    t = len(corner_u)
    polar_distance = 0.5 - np.abs(corner_v - 0.5)
    c = np.argmin(polar_distance, axis=1)
    a, b = (c + 1) % 3, (c + 2) % 3
    rows = np.arange(t)
    u_a, u_b = corner_u[rows, a], corner_u[rows, b]
    north = corner_v[rows, c] >= 0.5
    u_b = np.where(north, u_a + np.mod(u_b - u_a, 1.0), u_b)
    u_a = np.where(north, u_a, u_b + np.mod(u_a - u_b, 1.0))
    out = np.empty((t, 3, 2))
    out[..., 1] = corner_v
    out[rows, a, 0] = u_a
    out[rows, b, 0] = u_b
    out[rows, c, 0] = 0.5 * (u_a + u_b)
    return out


def pole_triangles(sphere_vertices, faces):
    """Indices of the triangles that contain a pole strictly inside (their uv is necessarily distorted).

    Examples
    --------
    >>> from sphere_nlp.shapes import octahedron
    >>> V, F = octahedron()
    >>> pole_triangles(V, F).tolist()       # the octahedron's poles are vertices
    []
    """
    from .certify import signed_solid_angles

    X = np.asarray(sphere_vertices, float)
    faces = np.asarray(faces, np.int64)
    inside = []
    for pole in ([0.0, 0.0, 1.0], [0.0, 0.0, -1.0]):
        # The pole is inside triangle (a, b, c) when the three triangles it makes with the triangle's
        # edges are all counter-clockwise.
        points = np.vstack([X, pole])
        p = len(X)
        ccw = np.ones(len(faces), bool)
        for j in range(3):
            a, b = faces[:, j], faces[:, (j + 1) % 3]
            ccw &= signed_solid_angles(points, np.c_[a, b, np.full(len(faces), p)]) > 0
        inside.append(np.flatnonzero(ccw))
    return np.unique(np.concatenate(inside))


def uv_signed_areas(corner_uv):
    """Signed area of each triangle in the uv plane, (t,); positive for counter-clockwise.

    Examples
    --------
    >>> uv_signed_areas(np.array([[[0, 0], [1, 0], [0, 1]]], float)).tolist()
    [0.5]
    """
    d1 = corner_uv[:, 1] - corner_uv[:, 0]
    d2 = corner_uv[:, 2] - corner_uv[:, 0]
    return 0.5 * (d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0])


def checker(corner_uv, squares=(16, 8)):
    """Checkerboard value (0 or 1) at texture coordinates, with ``squares`` = (along u, along v).

    Squares are whole in both directions, so u and u + 1 give the same value (the texture repeats).

    Examples
    --------
    >>> checker(np.array([[0.01, 0.01], [0.07, 0.01], [1.01, 0.01]])).tolist()
    [0, 1, 0]
    """
    corner_uv = np.asarray(corner_uv, float)
    i = np.floor(corner_uv[..., 0] * squares[0]).astype(np.int64)
    j = np.floor(corner_uv[..., 1] * squares[1]).astype(np.int64)
    return (i + j) % 2


# Light and dark grey, RGB: neutral, so the checkerboard is not mistaken for a distortion colour
# (the pictures draw it with these too, sphere_nlp.picture).
CHECKER_COLOURS = ((238, 238, 238), (80, 80, 88))


def checker_image(squares=(16, 8), pixels_per_square=64):
    """An RGB checkerboard texture (height, width, 3) uint8 matching :func:`checker` under OBJ's
    convention (v = 0 at the image's bottom row), ``squares`` = (along u, along v).

    Examples
    --------
    >>> image = checker_image(pixels_per_square=4)
    >>> image.shape, image.dtype.name
    ((32, 64, 3), 'uint8')
    >>> bottom_left = image[-1, 0]                 # (u, v) near (0, 0): checker value 0
    >>> bool((bottom_left == CHECKER_COLOURS[0]).all())
    True
    """
    height, width = squares[1] * pixels_per_square, squares[0] * pixels_per_square
    u = (np.arange(width) + 0.5) / width
    v = 1 - (np.arange(height) + 0.5) / height     # image rows run top down, v bottom up
    uv = np.stack(np.broadcast_arrays(u[None, :], v[:, None]), axis=-1)
    return np.asarray(CHECKER_COLOURS, np.uint8)[checker(uv, squares)]


def split_at_seams(faces, corner_uv):
    """One vertex per distinct (vertex, uv) pair, for formats and libraries that take uv per vertex.

    Returns ``(source, new_faces, vertex_uv)``: ``source[k]`` is the original vertex that new vertex
    ``k`` copies, ``new_faces`` index the new vertices, ``vertex_uv`` is (k, 2). Vertices away from the
    seam and the poles keep one copy.

    Examples
    --------
    >>> from sphere_nlp.shapes import octahedron
    >>> V, F = octahedron()
    >>> source, new_faces, vertex_uv = split_at_seams(F, spherical_uv(V, F))
    >>> len(source) > len(V), bool((source[new_faces] == F).all())
    (True, True)
    """
    faces = np.asarray(faces, np.int64)
    corner_uv = np.asarray(corner_uv, float).reshape(-1, 2)
    keys = np.column_stack([faces.reshape(-1).astype(float), corner_uv])
    unique, inverse = np.unique(keys, axis=0, return_inverse=True)
    return unique[:, 0].astype(np.int64), inverse.reshape(faces.shape), unique[:, 1:]
