"""Starting points of the angle solve.

The log-chord solve starts from the angles and excesses of a *valid* spherical triangulation of the
mesh, which satisfy every constraint; the paper's formulations from a linear least-squares guess.

* :func:`conformal_start`: the linear spherical conformal map (:func:`sphere_nlp.conformal.conformal_map`)
  Mobius-centred by vertex area, its flipped triangles repaired by :func:`sphere_nlp.untangle.untangle`
  if it has any. Conformal to the metric of the target angles (:func:`initial_point`): in the
  angle modes close to their optimum, but not always bijective.
* :func:`embedding_start`: the convex embedding (:func:`sphere_nlp.embedding.convex_embedding`),
  valid by construction; the fallback.
* :func:`starting_positions`: the two above under one name (``kind``), then the Mobius gauge
  (:func:`sphere_nlp.embedding.excess_gauge` for the angle modes).
* :func:`checked_positions`: positions the caller gives (for instance a coarser mesh's solution
  carried over by :func:`prolong_to_subdivision`, the mesh hierarchy), certified first.
* :func:`linear_initial_guess`: the paper's start, the point nearest the targets on the linear
  constraints (6) and (7).
* :func:`initial_point`: one of the above, as the solver asks for it, with its angles and excesses
  (:func:`angles_and_excess`).

Plain numpy in and out.
"""

import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from . import interrupts
from .certify import certify
from .geometry import (corner_angles, scatter_to_vertices, signed_solid_angles, spherical_angles,
                       triangle_areas)
from .hierarchy import prolong_to_subdivision  # noqa: F401  (the hierarchy's start, re-exported)

# The named starting points of :func:`initial_point` (an (n, 3) array of positions is the other kind).
START_POINTS = ("auto", "conformal", "embedding", "linear")


@dataclass
class InitialPoint:
    """Where the angle solve starts.

    Attributes
    ----------
    angles : (t, 3) array
    excess : (t,) array
    positions : (n, 3) array or None
        The valid spherical triangulation the angles come from (None for the linear guess).
    kind : str
        "conformal", "conformal-untangled", "surface-conformal", "surface-conformal-untangled",
        "embedding", "embedding-uncentred", "embedding-invalid", "given" or "linear"
        (:func:`starting_positions`).
    """

    angles: np.ndarray
    excess: np.ndarray
    positions: np.ndarray
    kind: str


def angles_and_excess(positions, faces):
    """Corner angles (t, 3) and excesses (t,) of a valid spherical triangulation."""
    return spherical_angles(positions, faces), signed_solid_angles(positions, faces)


def vertex_areas(vertices, faces, n_vertices):
    """The 3D area of the triangles around each vertex (the Mobius centring's weights)."""
    return scatter_to_vertices(faces, triangle_areas(vertices, faces), n_vertices)


def conformal_start(connectivity, vertices, weights=None, angles=None, progress=None):
    """The conformal map, Mobius-centred by ``weights``, if it (or its untangled repair) certifies.

    ``angles`` (t, 3): map conformally to the metric these corner angles describe instead of the
    surface's (see :func:`sphere_nlp.conformal.conformal_map`). ``progress``: the untangling's
    progress function (:func:`sphere_nlp.untangle.untangle`).

    Returns
    -------
    (positions, kind) with kind "conformal" or "conformal-untangled", or None.
    """
    from .conformal import NESTED_DISSECTION_UNKNOWNS, conformal_map
    from .embedding import mobius_centre

    faces = connectivity.faces
    # The mesh's nested-dissection order, shared with the unfold's solves (computed once).
    order = connectivity.vertex_order() if connectivity.n_vertices >= NESTED_DISSECTION_UNKNOWNS else None
    with np.errstate(all="ignore"):
        positions = mobius_centre(conformal_map(vertices, faces, angles=angles, vertex_order=order), weights)
    if not np.isfinite(positions).all():
        return None
    if certify(positions, faces).valid:
        return positions, "conformal"
    if interrupts.deadline_passed():
        return None                 # no time left to repair it (see starting_positions)
    # A few flipped triangles (knight 57, cheburashka 38, max_planck 2, nefertiti 1): re-embed
    # small disks around them, which keeps the map conformal elsewhere.
    from .untangle import untangle
    repaired, _ = untangle(positions, faces, mesh_vertices=vertices, progress=progress)
    if repaired is not None and certify(repaired, faces).valid:
        return repaired, "conformal-untangled"
    return None


def embedding_start(connectivity, vertices=None, weights=None):
    """The convex embedding (uniform weights), Mobius-centred by ``weights`` if that keeps it valid.

    Returns
    -------
    (positions, kind) with kind "embedding", "embedding-uncentred", or "embedding-invalid" where
    even the uncentred embedding fails its certificate (parts too thin for double precision: a
    valid embedding in exact arithmetic, rounded).
    """
    from .embedding import convex_embedding, mobius_centre, punctured_embedding

    faces = connectivity.faces
    positions = convex_embedding(connectivity, vertices, weights="uniform")
    convex_valid = certify(positions, faces).valid
    if not convex_valid:
        # Lost to floating point (a degree-1,000 cap's ring shrinks exponentially): the embedding
        # around its largest-degree vertex instead, which places that ring evenly on the equator.
        positions = punctured_embedding(connectivity)
    centred = mobius_centre(positions, weights)
    if certify(centred, faces).valid:
        return centred, "embedding"
    valid = convex_valid or certify(positions, faces).valid     # the convex one is certified already
    return positions, "embedding-uncentred" if valid else "embedding-invalid"


def starting_positions(connectivity, vertices=None, kind="auto", gauge="area", angles=None, progress=None):
    """Valid spherical positions of the mesh to start the log-chord solve from.

    ``"conformal"``: :func:`conformal_start`. Close to the optimum of every angle mode (brain,
    10,242 vertices, original-angles: 7 iterations instead of > 330 s from the embedding), but not
    always bijective. ``"embedding"``: :func:`embedding_start`, valid by construction. ``"auto"``
    (and ``"conformal"`` when it fails or there are no ``vertices``): the conformal start if it
    certifies, else the embedding.

    ``gauge="excess"`` then moves the start by the Mobius transformation minimising the sum of
    squared excesses (:func:`sphere_nlp.embedding.excess_gauge`), the normalisation of the angle
    modes' optimum (kept only if it certifies); ``"area"`` (default) keeps the area centring.

    ``angles`` (t, 3), optional: the conformal start maps conformally to the metric of these corner
    angles rather than the surface's (:func:`conformal_start`). ``progress``, optional: called
    while the conformal start's flipped triangles are repaired (:func:`sphere_nlp.untangle.untangle`).

    Returns
    -------
    positions : (n, 3) array of unit vectors, a certified spherical triangulation unless ``kind`` is
        "embedding-invalid"
    kind : str
        Which start was used: "conformal", "conformal-untangled", "surface-conformal",
        "surface-conformal-untangled" (the map conformal to ``angles`` could not be untangled, the
        surface's own could), "embedding", "embedding-uncentred", or "embedding-invalid" (no
        conformal map could be untangled and the embedding fails its certificate:
        :func:`embedding_start`).
    """
    faces = connectivity.faces
    weights = None if vertices is None else vertex_areas(vertices, faces, connectivity.n_vertices)
    found = None
    began = time.perf_counter()

    def announce(step):
        # Each part of the start takes tens of seconds at 700k vertices: say which one runs.
        if progress is not None:
            progress("start (%s)" % step, 0, 0, 0.0, time.perf_counter() - began)

    # Past the run's deadline (interrupts.deadline) only the embedding, one linear solve valid by
    # construction: the solve then stops at once and reports the limit.
    if kind in ("auto", "conformal") and vertices is not None and not interrupts.deadline_passed():
        announce("conformal map")
        found = conformal_start(connectivity, vertices, weights, angles, progress)
        if found is None and angles is not None and not interrupts.deadline_passed():
            # The targets' metric can fold a thin body past repair (a 50k eight-legged body's map to
            # 2 pi / deg: still folded after 80 s of untangling) and its convex embedding past double
            # precision, where the surface's own conformal map untangles.
            announce("conformal map of the surface")
            surface = conformal_start(connectivity, vertices, weights, None, progress)
            if surface is not None:
                found = surface[0], "surface-" + surface[1]
    if found is None:
        announce("convex embedding")
    positions, kind = found or embedding_start(connectivity, vertices, weights)
    if gauge == "excess" and not interrupts.deadline_passed():
        announce("Mobius gauge")
        from .embedding import excess_gauge
        moved = excess_gauge(positions, faces)
        if moved is not positions and certify(moved, faces).valid:
            return moved, kind
    return positions, kind


def feasible_start(connectivity, vertices=None, kind="auto", gauge="area", angles=None, progress=None):
    """Angles and excesses of a valid spherical triangulation of the mesh, and its positions.

    See :func:`starting_positions` for ``kind``, ``angles`` and ``progress``.

    Returns
    -------
    angles : (t, 3) array
    excess : (t,) array
    positions : (n, 3) array
    kind : str
    """
    positions, kind = starting_positions(connectivity, vertices, kind, gauge, angles, progress)
    return (*angles_and_excess(positions, connectivity.faces), positions, kind)


def checked_positions(connectivity, positions):
    """``positions`` as a float array if they are a certified spherical triangulation of the mesh,
    else UsageError naming what is wrong."""
    from .errors import UsageError

    positions = np.asarray(positions, dtype=float)
    if positions.shape != (connectivity.n_vertices, 3):
        raise UsageError("start positions must be a (%d, 3) array, not %s"
                         % (connectivity.n_vertices, positions.shape))
    certificate = certify(positions, connectivity.faces)
    if not certificate.valid:
        raise UsageError("start positions are not a valid spherical map of the mesh: " + certificate.reason)
    return positions


def linear_initial_guess(connectivity, targets):
    """Closest point to (beta, e') satisfying (6) and (7) exactly, by a sparse least-squares solve.

    Minimises ||alpha - beta||^2 + ||e - e'||^2 subject to alpha0 + alpha1 + alpha2 - e = pi per
    triangle and the angle sum 2 pi at every vertex.

    Returns
    -------
    angles : (t, 3) array
    excess : (t,) array

    Examples
    --------
    >>> from sphere_nlp.shapes import tetrahedron
    >>> from sphere_nlp.connectivity import build_connectivity
    >>> from sphere_nlp.targets import make_targets
    >>> V, F = tetrahedron()
    >>> c = build_connectivity(F, 4)
    >>> angles, excess = linear_initial_guess(c, make_targets("original-angles", V, F, c.vertex_degree))
    >>> np.allclose(angles, 2 * np.pi / 3), np.allclose(excess, np.pi)
    (True, True)
    """
    t, n = connectivity.n_faces, connectivity.n_vertices
    triangle_sum = sp.csr_matrix((np.ones(3 * t), (np.repeat(np.arange(t), 3), np.arange(3 * t))),
                                 shape=(t, 3 * t))
    A = sp.vstack([sp.hstack([triangle_sum, -sp.identity(t)]),
                   sp.hstack([connectivity.vertex_corner_matrix(), sp.csr_matrix((n, t))])]).tocsr()
    b = np.concatenate([np.full(t, np.pi), np.full(n, 2 * np.pi)])
    x_target = np.concatenate([targets.angles.ravel(), targets.excess])
    # (6) and (7) are independent (summing (7) minus summing (6) leaves sum(e)), so A A^T is
    # positive definite and the minimum-norm correction is unique.
    y = spla.spsolve((A @ A.T).tocsc(), b - A @ x_target)
    x = x_target + A.T @ y
    return x[:3 * t].reshape(t, 3), x[3 * t:]


def initial_point(connectivity, targets, start, vertices=None, gauge="area", progress=None):
    """The solver's starting point.

    Parameters
    ----------
    connectivity : Connectivity
    targets : Targets
    start : {"auto", "conformal", "embedding", "linear"} or (n, 3) array
        A named start (see :func:`starting_positions`; "linear": :func:`linear_initial_guess`), or
        positions, which must certify (:func:`checked_positions`).
    vertices : (n, 3) array, optional
        3D positions, for the conformal start and the centring weights.
    gauge : {"area", "excess"}
        The Mobius gauge of a named valid start (see :func:`starting_positions`).
    progress : callable(stage, step, value, 0.0, seconds), optional
        Progress of a long start (see :func:`starting_positions`).

    The conformal start maps conformally to the metric of ``targets.angles``: the surface's own
    angles in the original modes, 2 pi / deg in the equal modes, whose optima are far from the
    surface's conformal map (equal-angles iterations from the surface's map -> from the targets'
    metric: knight.off 88 -> 12, max_planck.obj 109 -> 14, koala.obj over 347 in 15 minutes -> 7;
    equal-areas armadillo.obj 1,224 -> 607; docs/tuning.md, "The start's metric").

    Returns
    -------
    InitialPoint
    """
    if not isinstance(start, str):
        positions = checked_positions(connectivity, start)
        return InitialPoint(*angles_and_excess(positions, connectivity.faces), positions, "given")
    if start not in START_POINTS:
        raise ValueError("start must be one of %s" % (START_POINTS,))
    if start == "linear":
        return InitialPoint(*linear_initial_guess(connectivity, targets), None, "linear")
    angles, excess, positions, kind = feasible_start(connectivity, vertices, start, gauge,
                                                     _metric_angles(connectivity, targets, vertices), progress)
    return InitialPoint(angles, excess, positions, kind)


def _metric_angles(connectivity, targets, vertices):
    """The target angles, or None when they are the surface's own angles, whose conformal map is
    then computed from the vertices (the same map, without the rounding of rebuilding the
    triangles)."""
    if vertices is None:
        return None
    own = corner_angles(np.asarray(vertices, dtype=float), connectivity.faces)
    return None if np.allclose(targets.angles, own, rtol=0, atol=1e-12) else targets.angles
