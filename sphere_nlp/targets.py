"""Targets of the objective (9): corner angles beta, triangle excesses e', and the weights of both terms.

The objective sphere_nlp minimises is

    f = angle_weight * sum (alpha - beta)^2  +  area_weight * sum ((e - e') / e_mean)^2

with ``e_mean = 4 pi / t`` the mean spherical excess. Dividing the excess error by ``e_mean`` is the
paper's (9) with the excess term scaled by ``1 / e_mean^2``: excesses shrink like 1/t, so the raw term
would fade away on large meshes while the angle term does not; in relative units both terms grow like t
and keep their balance at every mesh size.

Modes (the names of the paper's Fig. 3):

============== ======================================= ======================================= ========
mode           beta                                    e'                                      weights
============== ======================================= ======================================= ========
equal-angles   2 pi / deg(v) at every corner of v      4 pi / t                                1, 0
equal-areas    2 pi / deg(v)                           4 pi / t                                0.01, 1
original-angles the mesh's 3D corner angles            3D areas scaled to sum 4 pi             1, 0
original-areas the mesh's 3D corner angles             3D areas scaled to sum 4 pi             0.01, 1
============== ======================================= ======================================= ========

``2 pi / deg(v)`` is the only "equal" angle that constraint (7) allows at every vertex. The angle modes
use the angle term alone, as the paper's figure does. The area modes keep a small angle term (weight
0.01): triangle areas alone leave the map almost undetermined (about two degrees of freedom but many
nearby minima), and the weak angle term picks the least distorted of them without visibly giving up
area accuracy.

Corner weighting (``corner_weighting``): ``"uniform"`` is the paper's (9) verbatim, every corner's
squared error counted alike, so closing a 2 degree corner costs almost nothing and the optimum can
collapse small corners. ``"relative"`` charges relative errors instead, as angle-based flattening
does (Sheffer & de Sturler 2001): weights 1 / beta^2, multiplied by the mean beta^2 so that the term
keeps its magnitude (and the weights are 1 wherever all targets are equal):

    f = angle_weight * sum w (alpha - beta)^2 + ...,   w = mean(beta^2) / beta^2
"""

from dataclasses import dataclass

import numpy as np

from .geometry import corner_angles, triangle_areas
from .names import CORNER_WEIGHTINGS, MODES  # noqa: F401  (defined there for a light --help)

# Relative in the angle modes (worst quasi-conformal ratio on cheburashka.off 661 -> 85 with the
# floors, mean angle distortion +4%); the area modes keep (9) (relative measured worse there:
# penguin.obj original-areas QC max 727 -> 2977). See docs/tuning.md, "corner_weighting".
DEFAULT_CORNER_WEIGHTING = {
    "equal-angles": "relative",
    "equal-areas": "uniform",
    "original-angles": "relative",
    "original-areas": "uniform",
}

DEFAULT_WEIGHTS = {
    "equal-angles": (1.0, 0.0),
    "equal-areas": (0.01, 1.0),
    "original-angles": (1.0, 0.0),
    "original-areas": (0.01, 1.0),
}


@dataclass(frozen=True)
class Targets:
    """Targets and weights of the objective.

    Attributes
    ----------
    angles : (t, 3) float array
        Target corner angles beta (radians).
    excess : (t,) float array
        Target spherical excesses e' (radians, i.e. areas on the unit sphere).
    angle_weight, area_weight : float
        Weights of the two terms (see the module docstring for the scaling of the area term).
    mode : str
        The mode name, or "custom".
    corner_weighting : {"relative", "uniform"}
        How the angle term weighs each corner (see the module docstring); ``corner_weights``.
    """

    angles: np.ndarray
    excess: np.ndarray
    angle_weight: float
    area_weight: float
    mode: str
    corner_weighting: str = "uniform"

    @property
    def corner_weights(self):
        """Weight of each corner's squared error in the angle term, (t, 3): ones for "uniform",
        mean(beta^2) / beta^2 for "relative"."""
        if self.corner_weighting == "uniform":
            return np.ones_like(self.angles)
        squared = np.asarray(self.angles, float) ** 2
        return squared.mean() / squared

    @property
    def excess_scale(self):
        """The unit of the area term, the mean excess 4 pi / t."""
        return 4 * np.pi / len(self.excess)


def make_targets(mode, vertices, faces, vertex_degree, angle_weight=None, area_weight=None,
                 target_angles=None, target_excess=None, corner_weighting=None):
    """Build the targets of one mode, optionally overriding weights or the targets themselves.

    Parameters
    ----------
    mode : str
        One of :data:`MODES`.
    vertices : (n, 3) float array
    faces : (t, 3) int array
    vertex_degree : (n,) int array
    angle_weight, area_weight : float, optional
        Override the mode's weights (non-negative, not both zero).
    target_angles : (t, 3) array, optional
        Custom corner targets beta, replacing the mode's.
    target_excess : (t,) array, optional
        Custom excess targets e', replacing the mode's; they are rescaled to sum to 4 pi.
    corner_weighting : {"relative", "uniform"}, optional
        Weights of the corners in the angle term (default by mode,
        :data:`DEFAULT_CORNER_WEIGHTING`: relative in the angle modes, uniform in the area modes);
        "uniform" is the paper's (9).

    Returns
    -------
    Targets

    Examples
    --------
    >>> from sphere_nlp.shapes import octahedron
    >>> V, F = octahedron()
    >>> tg = make_targets("equal-angles", V, F, np.full(6, 4))
    >>> float(tg.angles[0, 0]), float(tg.excess.sum() / np.pi)
    (1.5707963267948966, 4.0)
    """
    from .errors import UsageError

    if mode not in MODES:
        raise UsageError("unknown target mode %r; choose one of %s" % (mode, ", ".join(MODES)))
    t = len(faces)
    if mode.startswith("equal"):
        angles = np.broadcast_to(2 * np.pi / vertex_degree[faces], (t, 3)).astype(float)
        excess = np.full(t, 4 * np.pi / t)
    else:
        angles = corner_angles(vertices, faces)
        areas = triangle_areas(vertices, faces)
        excess = 4 * np.pi * areas / areas.sum()
    default_angle_weight, default_area_weight = DEFAULT_WEIGHTS[mode]
    custom = False
    if target_angles is not None:
        angles = np.array(target_angles, dtype=float)
        if angles.shape != (t, 3) or not np.isfinite(angles).all():
            raise UsageError("target_angles must be a finite (t, 3) array, t = %d" % t)
        custom = True
    if target_excess is not None:
        excess = np.array(target_excess, dtype=float)
        if excess.shape != (t,) or not np.isfinite(excess).all() or excess.sum() <= 0:
            raise UsageError("target_excess must be a finite (t,) array with a positive sum, t = %d" % t)
        excess = excess * (4 * np.pi / excess.sum())
        custom = True
    angle_weight = default_angle_weight if angle_weight is None else float(angle_weight)
    area_weight = default_area_weight if area_weight is None else float(area_weight)
    if angle_weight < 0 or area_weight < 0 or angle_weight + area_weight == 0:
        raise UsageError("weights must be non-negative and not both zero")
    corner_weighting = DEFAULT_CORNER_WEIGHTING[mode] if corner_weighting is None else corner_weighting
    if corner_weighting not in CORNER_WEIGHTINGS:
        raise UsageError("unknown corner weighting %r; choose one of %s"
                         % (corner_weighting, ", ".join(CORNER_WEIGHTINGS)))
    if corner_weighting == "relative" and not (angles > 0).all():
        raise UsageError("corner_weighting 'relative' needs every target angle positive")
    return Targets(angles=angles, excess=excess, angle_weight=angle_weight, area_weight=area_weight,
                   mode=mode if not custom else "custom", corner_weighting=corner_weighting)
