"""Distortion of a spherical map, computed from the sphere positions and the input mesh.

Every measure compares each input triangle with its image: the *chord triangle* (the flat triangle
spanned by the three sphere positions) for angles and the affine map, the *spherical triangle*
(signed solid angle, :func:`sphere_nlp.certify.signed_solid_angles`) for areas. All functions take
numpy arrays and return numpy arrays, except :func:`distortion_summary`, which returns plain
JSON-safe Python numbers.

Conventions for flipped triangles (signed solid angle <= 0, i.e. clockwise seen from outside the
sphere, or degenerate): :func:`quasi_conformal_ratio` is ``inf`` and :func:`area_log_ratio` is
``nan`` (``-inf`` for zero area), while :func:`angle_distortion` is finite (planar angles are
unsigned, so it cannot see a flip; the ``flipped`` count of the summary does).
"""

import numpy as np

from .certify import certify
from .geometry import (corner_angles, cross, signed_solid_angles, spherical_angles, triangle_areas,  # noqa: F401
                       triangles_with_angles)

SUMMARY_KEYS = ("valid", "flipped", "degree", "max_norm_error", "mean_abs_angle_diff_deg",
                "max_abs_angle_diff_deg", "qc_mean", "qc_max", "mean_abs_log_area", "area_cv",
                "min_spherical_angle_deg")


def _arrays(vertices, faces):
    return np.asarray(vertices, dtype=float), np.asarray(faces, dtype=np.int64)


def angle_distortion(mesh_vertices, sphere_vertices, faces):
    """Absolute difference of chord-triangle and 3D corner angles, (t, 3), radians.

    Zero for every triangle exactly when each chord triangle is similar to its input triangle
    (e.g. a uniformly scaled mesh). Blind to flips; see the module docstring.

    Examples
    --------
    >>> from sphere_nlp.shapes import icosphere
    >>> V, F = icosphere(1)
    >>> float(angle_distortion(V, 3 * V, F).max()) < 1e-12
    True
    """
    return np.abs(corner_angles(sphere_vertices, faces) - corner_angles(mesh_vertices, faces))


def _triangle_frames(vertices, faces):
    """Edge vectors of each triangle in its own orthonormal frame, (t, 2, 2), columns e1 and e2.

    The frame's x axis is along the first edge and its y axis in the triangle's plane toward the third
    corner, so the second coordinate of e2 is >= 0 (twice the area over |e1|).
    """
    P = vertices[faces]
    e1 = P[:, 1] - P[:, 0]
    e2 = P[:, 2] - P[:, 0]
    length1 = np.linalg.norm(e1, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        x2 = np.einsum("ij,ij->i", e1, e2) / length1
        y2 = np.linalg.norm(cross(e1, e2), axis=1) / length1
    frames = np.zeros((len(faces), 2, 2))
    frames[:, 0, 0] = length1
    frames[:, 0, 1] = x2
    frames[:, 1, 1] = y2
    return frames


def quasi_conformal_ratio(mesh_vertices, sphere_vertices, faces):
    """Ratio sigma1 / sigma2 >= 1 of each triangle's affine map from 3D triangle to chord triangle, (t,).

    1 for a similarity (angle-preserving), large for a strongly sheared or stretched triangle;
    ``inf`` for a flipped or degenerate image (signed solid angle <= 0 about the origin, the centre of
    the sphere) or a degenerate input triangle.

    The Jacobian J is 2 x 2 in per-triangle frames. Writing J = [[a, b], [c, d]], its conformal part
    has size Q = |(a + d, c - b)| / 2 and its anti-conformal part R = |(a - d, c + b)| / 2; then
    sigma1 = Q + R, sigma2 = Q - R, so the ratio is computed without the cancellation of
    ``sqrt(K**2 - 1)``-style formulas near 1.

    Examples
    --------
    >>> V = np.array([[0, 0, 1], [1, 0, 1], [0, 1, 1]], float)
    >>> F = np.array([[0, 1, 2]])
    >>> quasi_conformal_ratio(V, V * [2, 1, 1], F).round(12)   # stretch x by 2
    array([2.])
    """
    mesh_vertices, faces = _arrays(mesh_vertices, faces)
    sphere_vertices = np.asarray(sphere_vertices, dtype=float)
    source = _triangle_frames(mesh_vertices, faces)
    image = _triangle_frames(sphere_vertices, faces)
    # J @ source = image for the edge vectors; source is upper triangular, invert it in closed form.
    s11, s12, s22 = source[:, 0, 0], source[:, 0, 1], source[:, 1, 1]
    with np.errstate(invalid="ignore", divide="ignore"):
        inverse = np.zeros_like(source)
        inverse[:, 0, 0] = 1 / s11
        inverse[:, 0, 1] = -s12 / (s11 * s22)
        inverse[:, 1, 1] = 1 / s22
        J = image @ inverse
        a, b, c, d = J[:, 0, 0], J[:, 0, 1], J[:, 1, 0], J[:, 1, 1]
        Q = 0.5 * np.hypot(a + d, c - b)
        R = 0.5 * np.hypot(a - d, c + b)
        ratio = (Q + R) / (Q - R)
    bad = ~(signed_solid_angles(sphere_vertices, faces) > 0) | ~(Q > R) | ~np.isfinite(ratio)
    ratio[bad] = np.inf
    return ratio


def target_shape_ratio(sphere_vertices, faces, target_angles):
    """:func:`quasi_conformal_ratio` of each triangle's affine map from its target shape to its chord
    triangle, (t,); the target shape is the planar triangle with the target angles
    (:func:`sphere_nlp.geometry.triangles_with_angles`).

    In the angle modes this measures how far the map is from the triangles it was asked for; for
    the original angles it equals :func:`quasi_conformal_ratio`, while for equal angles it does not
    charge the map for regularising the input's slivers, as the 3D ratio does.

    Examples
    --------
    >>> S = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    >>> F = np.array([[0, 1, 2]])
    >>> target_shape_ratio(S, F, np.full((1, 3), np.pi / 3)).round(12)   # equilateral, as asked
    array([1.])
    """
    faces = np.asarray(faces, dtype=np.int64)
    sphere_vertices = np.asarray(sphere_vertices, dtype=float)
    t = len(faces)
    corners = np.arange(3 * t).reshape(t, 3)
    # Each triangle's corners copied apart: the targets share no vertices (the copies on the sphere
    # are the same points, so the orientation test is unchanged).
    return quasi_conformal_ratio(triangles_with_angles(target_angles).reshape(-1, 3),
                                 sphere_vertices[faces].reshape(-1, 3), corners)


def normalised_areas_3d(mesh_vertices, faces):
    """3D triangle areas scaled so that they sum to 4 pi (the area of the unit sphere), (t,)."""
    mesh_vertices, faces = _arrays(mesh_vertices, faces)
    areas = triangle_areas(mesh_vertices, faces)
    return areas * (4 * np.pi / areas.sum())


def area_log_ratio(mesh_vertices, sphere_vertices, faces):
    """log(spherical area / normalised 3D area) of each triangle, (t,).

    The spherical area is the signed solid angle of the triangle's image, the 3D areas are scaled to
    sum to 4 pi, so 0 means the triangle keeps its share of the surface, +log 2 that it doubles it.
    ``nan`` for flipped images (negative solid angle), ``-inf`` for zero-area images.

    Examples
    --------
    >>> from sphere_nlp.shapes import octahedron
    >>> V, F = octahedron()
    >>> bool(np.allclose(area_log_ratio(V, V, F), 0))   # 8 equal triangles, each pi / 2
    True
    """
    mesh_vertices, faces = _arrays(mesh_vertices, faces)
    omega = signed_solid_angles(np.asarray(sphere_vertices, dtype=float), faces)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.log(omega / normalised_areas_3d(mesh_vertices, faces))


def per_vertex_mean(faces, face_values, n_vertices):
    """Mean of the finite values of the faces around each vertex, (n,), e.g. to colour a picture.

    Non-finite face values (flipped triangles) are left out; a vertex with none gets ``nan``.

    Examples
    --------
    >>> per_vertex_mean(np.array([[0, 1, 2], [0, 2, 3]]), np.array([1.0, 3.0]), 4)
    array([2., 1., 2., 3.])
    """
    faces = np.asarray(faces, dtype=np.int64)
    face_values = np.asarray(face_values, dtype=float)
    finite = np.isfinite(face_values)
    total = np.zeros(n_vertices)
    count = np.zeros(n_vertices)
    for k in range(3):
        np.add.at(total, faces[finite, k], face_values[finite])
        np.add.at(count, faces[finite, k], 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return total / count


def distortion_fields(mesh_vertices, sphere_vertices, faces):
    """A map's distortion where it happens: per face and per vertex arrays, to colour or analyse.

    Returns a dict of arrays: ``face_log_area_ratio`` (:func:`area_log_ratio`, (t,)),
    ``face_angle_distortion_deg`` (mean of :func:`angle_distortion` over the corners, (t,)),
    ``corner_angle_distortion_deg`` ((t, 3)), ``face_quasi_conformal`` (:func:`quasi_conformal_ratio`,
    (t,)), and ``vertex_log_area_ratio``, ``vertex_angle_distortion_deg`` (:func:`per_vertex_mean`
    of the face values, (n,)). Their means are :func:`distortion_summary`'s.

    Examples
    --------
    >>> from sphere_nlp.shapes import octahedron
    >>> V, F = octahedron()
    >>> d = distortion_fields(V, V, F)
    >>> d["vertex_log_area_ratio"].shape, float(np.abs(d["face_angle_distortion_deg"]).max()) < 1e-12
    ((6,), True)
    """
    mesh_vertices, faces = _arrays(mesh_vertices, faces)
    corners = np.degrees(angle_distortion(mesh_vertices, sphere_vertices, faces))
    log_area = area_log_ratio(mesh_vertices, sphere_vertices, faces)
    n = len(sphere_vertices)
    return {"face_log_area_ratio": log_area, "face_angle_distortion_deg": corners.mean(axis=1),
            "corner_angle_distortion_deg": corners,
            "face_quasi_conformal": quasi_conformal_ratio(mesh_vertices, sphere_vertices, faces),
            "vertex_log_area_ratio": per_vertex_mean(faces, log_area, n),
            "vertex_angle_distortion_deg": per_vertex_mean(faces, corners.mean(axis=1), n)}


def _json_float(value):
    """A float for JSON: non-finite values become None (JSON has no inf or nan)."""
    value = float(value)
    return value if np.isfinite(value) else None


def distortion_summary(mesh_vertices, sphere_vertices, faces):
    """Validity and distortion of a spherical map in one JSON-safe dict.

    Keys
    ----
    valid, flipped, degree, max_norm_error
        From :func:`sphere_nlp.certify.certify` (bool, int, float, float).
    mean_abs_angle_diff_deg, max_abs_angle_diff_deg
        Mean and max of :func:`angle_distortion` over all corners, degrees.
    qc_mean, qc_max
        :func:`quasi_conformal_ratio`, mean weighted by 3D area and max, over the triangles where it is
        finite (the ``flipped`` ones are left out and counted there instead).
    mean_abs_log_area
        Mean of |:func:`area_log_ratio`| over the triangles where it is finite (not weighted).
    area_cv
        Coefficient of variation (std / mean) of the signed spherical triangle areas, all triangles:
        0 when all triangles have equal area on the sphere.
    min_spherical_angle_deg
        Smallest spherical corner angle (:func:`sphere_nlp.certify.spherical_angles`), degrees;
        negative when a triangle is flipped.

    A value that is not finite (no finite triangle to average over, positions with nan) is None.

    Examples
    --------
    >>> from sphere_nlp.shapes import octahedron
    >>> V, F = octahedron()
    >>> s = distortion_summary(V, V, F)
    >>> s["valid"], s["flipped"], s["qc_max"], round(s["min_spherical_angle_deg"], 9)
    (True, 0, 1.0, 90.0)
    """
    mesh_vertices, faces = _arrays(mesh_vertices, faces)
    sphere_vertices = np.asarray(sphere_vertices, dtype=float)
    certificate = certify(sphere_vertices, faces)
    angle_diff = np.degrees(angle_distortion(mesh_vertices, sphere_vertices, faces))
    qc = quasi_conformal_ratio(mesh_vertices, sphere_vertices, faces)
    qc_finite = np.isfinite(qc)
    weights = normalised_areas_3d(mesh_vertices, faces)[qc_finite]
    log_area = np.abs(area_log_ratio(mesh_vertices, sphere_vertices, faces))
    log_area = log_area[np.isfinite(log_area)]
    omega = signed_solid_angles(sphere_vertices, faces)
    nan = float("nan")
    with np.errstate(invalid="ignore", divide="ignore"):
        summary = {
            "valid": bool(certificate.valid),
            "flipped": int(certificate.flipped),
            "degree": _json_float(certificate.degree),
            "max_norm_error": _json_float(certificate.max_norm_error),
            "mean_abs_angle_diff_deg": _json_float(angle_diff.mean()),
            "max_abs_angle_diff_deg": _json_float(angle_diff.max()),
            "qc_mean": _json_float((weights * qc[qc_finite]).sum() / weights.sum()
                                   if qc_finite.any() else nan),
            "qc_max": _json_float(qc[qc_finite].max() if qc_finite.any() else nan),
            "mean_abs_log_area": _json_float(log_area.mean() if len(log_area) else nan),
            "area_cv": _json_float(omega.std() / omega.mean()),
            "min_spherical_angle_deg": _json_float(np.degrees(spherical_angles(sphere_vertices, faces).min())),
        }
    return summary


USABILITY_KEYS = ("valid", "flipped", "qc_max", "qc_max_target", "sliver_targets", "corners_below_fraction",
                  "min_area_ratio", "mean_abs_angle_diff_deg", "mean_abs_log_area")

# Targets with a corner below this (radians, 1 degree) are slivers: a map that keeps such a corner to
# within a few per cent can still shear the triangle by a ratio in the hundreds (koala.obj's worst, a
# 0.08/179.84/0.08-degree triangle kept to 0.003 degrees, measures 1,556 without the solve's sliver
# band), so the ratio against the targets is reported over the other triangles, and the ratio
# against the 3D shapes (qc_max) is the one that charges slivers.
SLIVER_TARGET_ANGLE = np.radians(1.0)


def usability_summary(mesh_vertices, sphere_vertices, faces, target_angles=None, corner_fraction=0.1, summary=None):
    """Whether a spherical map is usable for texturing and resampling, from positions alone.

    An independent check of the solver's output (it reads neither the solver's angles nor its
    bounds): a certified map can still have collapsed triangles or triangles too small for double
    precision to place.

    Parameters
    ----------
    mesh_vertices, sphere_vertices : (n, 3) arrays
    faces : (t, 3) int array
    target_angles : (t, 3) array, optional
        The objective's target corner angles beta (default: the 3D corner angles).
    corner_fraction : float
        A spherical corner counts as collapsed below this fraction of its target.
    summary : dict, optional
        :func:`distortion_summary` of the same map, if the caller has it already.

    Returns
    -------
    dict (JSON-safe)
        ``valid``, ``flipped`` (the certificate); ``qc_max`` (worst :func:`quasi_conformal_ratio`,
        3D triangle to chord triangle; None if some triangle is flipped); ``qc_max_target`` (worst
        :func:`target_shape_ratio`, target shape to chord triangle, over the triangles whose targets
        have no corner below 1 degree; None if flipped or if every target is such a sliver) and
        ``sliver_targets`` (how many triangles that leaves out); ``corners_below_fraction``
        (spherical corners measured from the positions below ``corner_fraction`` x target);
        ``min_area_ratio`` (smallest signed solid angle over the mean 4 pi / t); the means
        ``mean_abs_angle_diff_deg`` and ``mean_abs_log_area`` of :func:`distortion_summary`.

    Examples
    --------
    >>> from sphere_nlp.shapes import octahedron
    >>> V, F = octahedron()
    >>> s = usability_summary(V, V, F)
    >>> s["qc_max"], round(s["qc_max_target"], 12), s["corners_below_fraction"], round(s["min_area_ratio"], 12)
    (1.0, 1.0, 0, 1.0)
    """
    mesh_vertices, faces = _arrays(mesh_vertices, faces)
    sphere_vertices = np.asarray(sphere_vertices, dtype=float)
    if target_angles is None:
        target_angles = corner_angles(mesh_vertices, faces)
    if summary is None:
        summary = distortion_summary(mesh_vertices, sphere_vertices, faces)
    qc = quasi_conformal_ratio(mesh_vertices, sphere_vertices, faces)
    omega = signed_solid_angles(sphere_vertices, faces)
    target_angles = np.asarray(target_angles, float)
    below = spherical_angles(sphere_vertices, faces) < corner_fraction * target_angles
    shaped = target_angles.min(axis=1) >= SLIVER_TARGET_ANGLE
    shape_ratio = target_shape_ratio(sphere_vertices, faces, target_angles)[shaped]
    return {
        "valid": summary["valid"],
        "flipped": summary["flipped"],
        "qc_max": _json_float(qc.max()),
        "qc_max_target": _json_float(shape_ratio.max()) if len(shape_ratio) else None,
        "sliver_targets": int((~shaped).sum()),
        "corners_below_fraction": int(below.sum()),
        "min_area_ratio": _json_float(omega.min() / (4 * np.pi / len(faces))),
        "mean_abs_angle_diff_deg": summary["mean_abs_angle_diff_deg"],
        "mean_abs_log_area": summary["mean_abs_log_area"],
    }


# A map has shrunk a region past use when its triangles average more than a factor e from their
# share of the surface (mean |log area ratio| above this), or when this much of the surface's 3D
# area lies in triangles below SHRUNK_SHARE of their share: a texture or a resampling shows one
# texel there. Conformal maps shrink protrusions exponentially in their length over their girth.
SHRUNK_MEAN_ABS_LOG_AREA = 1.0
SHRUNK_SHARE = 1e-6
SHRUNK_SURFACE_FRACTION = 1e-3


def _percent(fraction):
    """A fraction of the surface as a percentage that is never printed as 0 when it is not 0."""
    return "%.3g%%" % (100 * fraction)


def shrinkage_summary(mesh_vertices, sphere_vertices, faces, target):
    """How much of the surface a map has shrunk past use, and the line that says so (or None).

    Two measures, each with its threshold: the mean |log area ratio| (above
    :data:`SHRUNK_MEAN_ABS_LOG_AREA`: the triangles are on average more than a factor e off their
    share of the sphere) and the share of the surface in triangles below :data:`SHRUNK_SHARE` of
    their share (at least :data:`SHRUNK_SURFACE_FRACTION`). The line states the measure or measures
    that passed their thresholds, each with its number and threshold, so its words and numbers
    agree: a map shrunk on average but with no triangle below 1e-6 of its share is not said to have
    "0% of its area" anywhere.

    Parameters
    ----------
    mesh_vertices, sphere_vertices : (n, 3) arrays
    faces : (t, 3) int array
    target : str or None
        The run's mode: the line is for the angle modes, whose maps are free to shrink regions
        (an area mode keeps each triangle's share); None for a sphere of unknown mode, judged by
        its numbers alone.

    Returns
    -------
    dict (JSON-safe)
        ``mean_abs_log_area`` (:func:`distortion_summary`'s), ``shrunk_triangles`` (below
        :data:`SHRUNK_SHARE` of their share of the surface), ``shrunk_surface_fraction`` (their
        share of the 3D area), ``triggers`` (the measures past their thresholds: ``"mean"``,
        ``"surface"``; empty in an area mode), ``shrunk`` (any trigger) and ``note``: one line
        saying what triggered it and naming the mode that keeps the regions, or None.

    Examples
    --------
    >>> from sphere_nlp.shapes import octahedron
    >>> V, F = octahedron()
    >>> s = shrinkage_summary(V, V, F, "original-angles")
    >>> s["shrunk"], s["shrunk_triangles"], s["triggers"], s["note"]
    (False, 0, [], None)
    """
    mesh_vertices, faces = _arrays(mesh_vertices, faces)
    log_ratio = area_log_ratio(mesh_vertices, sphere_vertices, faces)
    finite = np.isfinite(log_ratio)
    mean_abs = float(np.abs(log_ratio[finite]).mean()) if finite.any() else float("nan")
    small = finite & (log_ratio < np.log(SHRUNK_SHARE))
    share = normalised_areas_3d(mesh_vertices, faces) / (4 * np.pi)
    fraction = float(share[small].sum())
    triggers = []
    if target is None or target.endswith("-angles"):
        if fraction >= SHRUNK_SURFACE_FRACTION:
            triggers.append("surface")
        if mean_abs > SHRUNK_MEAN_ABS_LOG_AREA:
            triggers.append("mean")
    note = None
    if triggers:
        reasons = []
        if "surface" in triggers:
            reasons.append("%s of the surface lies in triangles shrunk below %g of their share of the "
                           "sphere (%d triangles; the limit is %s)"
                           % (_percent(fraction), SHRUNK_SHARE, int(small.sum()), _percent(SHRUNK_SURFACE_FRACTION)))
        if "mean" in triggers:
            reasons.append("its triangles are on average a factor %.3g larger or smaller than their share "
                           "of the sphere (mean |log area ratio| %.2f; the limit is %g)"
                           % (np.exp(mean_abs), mean_abs, SHRUNK_MEAN_ABS_LOG_AREA))
        note = ("the map shrank parts of the surface past use: %s, as a conformal map does to limbs and "
                "other protrusions; --target original-areas keeps every part its size" % " and ".join(reasons))
    return {"mean_abs_log_area": _json_float(mean_abs), "shrunk_triangles": int(small.sum()),
            "shrunk_surface_fraction": fraction, "triggers": triggers, "shrunk": bool(triggers), "note": note}
