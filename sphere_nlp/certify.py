"""Certificate of a spherical map, computed from the positions exactly as they will be written."""

from dataclasses import dataclass, asdict

import numpy as np

NORM_TOLERANCE = 1e-9
DEGREE_TOLERANCE = 1e-9


@dataclass(frozen=True)
class Certificate:
    """Validity of sphere positions for a triangle mesh.

    Attributes
    ----------
    valid : bool
        Norm error < 1e-9, no flipped or degenerate triangle, |degree - 1| < 1e-9.
    flipped : int
        Triangles whose signed solid angle is <= 0 (flipped or degenerate) or not finite.
    degree : float
        Sum of signed solid angles over 4 pi.
    max_norm_error : float
        max | |x| - 1 | over the vertices.
    reason : str
        Empty when valid, otherwise what failed.
    """

    valid: bool
    flipped: int
    degree: float
    max_norm_error: float
    reason: str = ""

    def to_dict(self):
        return asdict(self)


def signed_solid_angles(positions, faces):
    """Signed solid angle of each spherical triangle (Van Oosterom & Strackee), (t,).

    Positive for triangles that are counter-clockwise seen from outside the sphere.
    """
    a, b, c = (positions[faces[:, k]] for k in range(3))
    # det[a, b, c] = a . ((b - a) x (c - a)): differences keep tiny triangles accurate.
    det = np.einsum("ij,ij->i", a, np.cross(b - a, c - a))
    na, nb, nc = (np.linalg.norm(p, axis=1) for p in (a, b, c))
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
    return np.arctan2(np.einsum("tjk,tjk->tj", a, np.cross(tb, tc)), np.einsum("tjk,tjk->tj", tb, tc))


def certify(positions, faces):
    """Check that positions are a valid degree-1 spherical map of the faces.

    Examples
    --------
    >>> from sphere_nlp.shapes import octahedron
    >>> V, F = octahedron()
    >>> certify(V, F).valid
    True
    >>> certify(V, F[:, ::-1]).flipped
    8
    """
    positions = np.asarray(positions, float)
    norms = np.linalg.norm(positions, axis=1)
    norm_error = float(np.max(np.abs(norms - 1))) if len(norms) else np.inf
    if not np.isfinite(norm_error):
        norm_error = float("inf")
    omega = signed_solid_angles(positions, faces)
    flipped = int(np.sum(~(omega > 0)))
    degree = float(np.sum(omega) / (4 * np.pi)) if np.isfinite(omega).all() else float("nan")
    reasons = []
    if not norm_error < NORM_TOLERANCE:
        reasons.append("vertices off the unit sphere by up to %.3g" % norm_error)
    if flipped:
        reasons.append("%d flipped or degenerate triangle(s)" % flipped)
    if not abs(degree - 1) < DEGREE_TOLERANCE:
        reasons.append("degree %.12g instead of 1" % degree)
    return Certificate(valid=not reasons, flipped=flipped, degree=degree, max_norm_error=norm_error,
                       reason="; ".join(reasons))
