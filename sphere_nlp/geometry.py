"""Shared geometric primitives of triangle meshes, in 3D and on the unit sphere.

One implementation of each, used by the targets, the starts, the certificate, the metrics and the
baselines. Plain numpy; ``faces`` index rows of the positions, corner ``[i, j]`` is at vertex
``faces[i, j]``.
"""

import numpy as np


def cross(u, v):
    """Cross product of 3-vectors along the last axis (broadcasting), as ``np.cross``.

    The same arithmetic as ``np.cross`` (bit for bit) without its axis handling and temporaries,
    several times faster on the 10^5-10^6 vectors that the certificate, the start's gauge and the
    unfold take at every step.

    >>> cross(np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])).tolist()
    [0.0, 0.0, 1.0]
    """
    u, v = np.asarray(u), np.asarray(v)
    out = np.empty(np.broadcast_shapes(u.shape, v.shape), dtype=np.result_type(u, v))
    out[..., 0] = u[..., 1] * v[..., 2] - u[..., 2] * v[..., 1]
    out[..., 1] = u[..., 2] * v[..., 0] - u[..., 0] * v[..., 2]
    out[..., 2] = u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]
    return out


def corner_angles(vertices, faces):
    """Planar corner angles of each triangle, (t, 3), ``[i, j]`` at vertex ``faces[i, j]``.

    Works for any triangles in 3D, e.g. the input mesh or the chord triangles of sphere positions.
    The angle is ``atan2(|cross|, dot)`` of the two edge vectors, accurate for needle-thin triangles
    (``arccos`` of a normalised dot product loses all digits near 0 and pi). Angles are unsigned, in
    [0, pi]; a degenerate triangle (coincident corners) gets 0 at the coincident corners.

    Examples
    --------
    >>> from sphere_nlp.shapes import octahedron
    >>> V, F = octahedron()
    >>> bool(np.allclose(corner_angles(V, F), np.pi / 3))
    True
    """
    P = np.asarray(vertices, dtype=float)[np.asarray(faces, dtype=np.int64)]   # (t, 3 corners, 3 coords)
    to_next = np.roll(P, -1, axis=1) - P
    to_prev = np.roll(P, 1, axis=1) - P
    sine = np.linalg.norm(cross(to_next, to_prev), axis=2)
    dot = np.einsum("tjk,tjk->tj", to_next, to_prev)
    return np.arctan2(sine, dot)


def triangle_areas(vertices, faces):
    """Area of each 3D triangle, (t,).

    >>> triangle_areas(np.eye(3), np.array([[0, 1, 2]])).round(4)
    array([0.866])
    """
    P = vertices[faces]
    return 0.5 * np.linalg.norm(cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]), axis=1)


def scatter_to_vertices(faces, face_values, n_vertices):
    """Per vertex, the sum of ``face_values`` over the triangles around it, (n,).

    With triangle areas: the area of each vertex's star; with a third of them, the lumped mass.
    """
    return np.bincount(np.asarray(faces).ravel(), weights=np.repeat(face_values, 3), minlength=n_vertices)


def area_weighted_centroid(vertices, faces):
    """The centroid of the surface (not of its vertices), so that dense regions do not pull it."""
    areas = triangle_areas(vertices, faces)
    return (areas[:, None] * vertices[faces].mean(axis=1)).sum(axis=0) / areas.sum()


def signed_solid_angles(positions, faces):
    """Signed solid angle of each spherical triangle (Van Oosterom & Strackee), (t,).

    Positive for triangles that are counter-clockwise seen from outside the sphere; for a valid map,
    the spherical excess of each triangle.
    """
    a, b, c = (positions[faces[:, k]] for k in range(3))
    # det[a, b, c] = a . ((b - a) x (c - a)): differences keep tiny triangles accurate.
    det = np.einsum("ij,ij->i", a, cross(b - a, c - a))
    norms = np.linalg.norm(positions, axis=1)       # once a vertex, not three times a triangle
    na, nb, nc = (norms[faces[:, k]] for k in range(3))
    denom = (na * nb * nc + np.einsum("ij,ij->i", a, b) * nc + np.einsum("ij,ij->i", b, c) * na
             + np.einsum("ij,ij->i", c, a) * nb)
    return 2 * np.arctan2(det, denom)


def spherical_angles(positions, faces):
    """Spherical corner angles of each triangle measured from positions, (t, 3).

    The angle at a is the angle between the tangents at a toward b and toward c; it is negative for
    a flipped triangle. Tangents are built from differences b - a, c - a, never from dot products
    close to 1, so the angles of tiny triangles keep their relative accuracy.
    """
    X = positions / np.linalg.norm(positions, axis=1, keepdims=True)
    P = X[faces]
    a, b, c = P, np.roll(P, -1, axis=1), np.roll(P, -2, axis=1)
    db, dc = b - a, c - a
    tb = db - np.einsum("tjk,tjk->tj", db, a)[..., None] * a
    tc = dc - np.einsum("tjk,tjk->tj", dc, a)[..., None] * a
    return np.arctan2(np.einsum("tjk,tjk->tj", a, cross(tb, tc)), np.einsum("tjk,tjk->tj", tb, tc))


def triangles_with_angles(angles):
    """Planar triangles with the given corner angles, (t, 3, 3) corner positions (z = 0).

    Each row of ``angles`` is scaled to sum to pi first (the spherical targets of the equal
    modes sum to slightly more), then the sides follow from the law of sines. For the 3D corner
    angles this is the input triangle up to a similarity.

    Examples
    --------
    >>> P = triangles_with_angles(np.array([[np.pi / 2, np.pi / 4, np.pi / 4]]))
    >>> np.linalg.norm(P[0, 1:] - P[0, 0], axis=1).round(12)     # the legs of a right isosceles triangle
    array([0.70710678, 0.70710678])
    """
    beta = np.asarray(angles, dtype=float)
    beta = beta * (np.pi / beta.sum(axis=1, keepdims=True))
    side = np.sin(beta)                      # side k is opposite corner k
    P = np.zeros((len(beta), 3, 3))
    P[:, 1, 0] = side[:, 2]
    P[:, 2, 0] = side[:, 1] * np.cos(beta[:, 0])
    P[:, 2, 1] = side[:, 1] * np.sin(beta[:, 0])
    return P


def rotation_between(a, b):
    """The rotation matrix R (3, 3) turning unit vector ``a`` to unit vector ``b`` by the smallest
    angle (Rodrigues); for opposite vectors the half-turn about X, or about Y when they lie on X.

    >>> R = rotation_between(np.array([0.0, 1, 0]), np.array([0.0, 0, 1]))
    >>> (R @ [0, 1, 0]).round(12).tolist(), (R @ [0, 0, 1]).round(12).tolist()
    ([0.0, 0.0, 1.0], [0.0, -1.0, 0.0])
    """
    a, b = np.asarray(a, float), np.asarray(b, float)
    axis = cross(a, b)
    sine, cosine = np.linalg.norm(axis), float(np.dot(a, b))
    if sine < 1e-12:
        if cosine > 0:
            return np.eye(3)
        return np.diag([1.0, -1.0, -1.0]) if abs(a[0]) < 0.9 else np.diag([-1.0, 1.0, -1.0])
    k = axis / sine
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + sine * K + (1 - cosine) * K @ K
