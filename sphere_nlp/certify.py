"""Certificate of a spherical map, computed from the positions exactly as they will be written."""

from dataclasses import dataclass, asdict

import numpy as np

from .geometry import signed_solid_angles, spherical_angles  # noqa: F401  (the certificate's measures)

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
