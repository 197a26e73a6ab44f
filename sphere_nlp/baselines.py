"""Baseline spherical maps to compare sphere_nlp against.

* :func:`alexa_relaxation`: the relaxation of Alexa (2000), the method of panel (b) of the paper's Fig. 3.
* :func:`conformal_map`: the linear spherical conformal map of Choi, Lam & Lui (2015, FLASH), the
  solver's default start (defined in :mod:`sphere_nlp.conformal`).
* :func:`cmcf_map`: conformalized mean curvature flow (Kazhdan, Solomon & Ben-Chen 2012).
* :func:`tutte_projection`: the valid-by-construction convex embedding sphere_nlp starts from.

All of them return positions whether or not the map is valid; check them with
:func:`sphere_nlp.certify.certify`.
"""

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from . import sparse_lu
from .certify import Certificate, certify
from .conformal import (beltrami_coefficient, conformal_map, cotan_laplacian, linear_beltrami_solver,  # noqa: F401
                        lumped_mass)
from .geometry import area_weighted_centroid, triangle_areas

STARTS = ("central", "normals")


@dataclass
class AlexaRelaxation:
    """Result of :func:`alexa_relaxation`.

    Attributes
    ----------
    positions : (n, 3) float array
        Vertex positions on the unit sphere, in input order.
    iterations : int
        Relaxation sweeps performed.
    converged : bool
        True when the largest vertex move of the last sweep fell below ``tol``.
    last_move : float
        Largest vertex move (Euclidean) of the last sweep.
    certificate : Certificate
        :func:`sphere_nlp.certify.certify` of ``positions``: convergence alone does not mean the map
        is valid (the relaxation can converge to a collapsed or folded configuration).
    """

    positions: np.ndarray
    iterations: int
    converged: bool
    last_move: float
    certificate: Certificate


def _edges(faces):
    """Unique undirected edges (m, 2) of a triangle mesh."""
    pairs = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return np.unique(np.sort(pairs, axis=1), axis=0)


def _alexa_start(vertices, faces, start):
    """Initial sphere positions: central projection from the centroid, or the Gauss map of normals."""
    if not isinstance(start, str):
        positions = np.array(start, dtype=float)
        if positions.shape != vertices.shape:
            raise ValueError("start positions must have shape %s" % (vertices.shape,))
    elif start == "central":
        positions = vertices - area_weighted_centroid(vertices, faces)
    elif start == "normals":
        # Area-weighted vertex normals: the Gauss map, for meshes not star-shaped about any point.
        P = vertices[faces]
        face_normals = np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])   # length = 2 * area
        positions = np.zeros_like(vertices)
        for k in range(3):
            np.add.at(positions, faces[:, k], face_normals)
    else:
        raise ValueError("start must be one of %s or an (n, 3) array" % (STARTS,))
    norms = np.linalg.norm(positions, axis=1, keepdims=True)
    if not (norms > 0).all():
        raise ValueError("a start position is at the centre; the central projection is undefined there")
    return positions / norms


def alexa_relaxation(vertices, faces, max_iter=10000, tol=1e-10, step=0.5, start="central",
                     edge_length_weights=True, recentre=True, anchors=None):
    """Spherical relaxation of Alexa (2000), "Merging polyhedral shapes with scattered features".

    Start from a map of the mesh onto the unit sphere, then repeat: move every vertex toward the
    weighted centroid of its neighbours and project it back onto the sphere, until no vertex moves
    more than ``tol``. What is implemented, and why:

    * **Start** (``start``): the central projection of the vertices from the mesh's centroid, which is
      a valid map for meshes star-shaped about it (the cylinder is); ``"normals"`` uses the Gauss map
      (area-weighted vertex normals) instead, for meshes that are not star-shaped.
    * **Edge-length weights** (``edge_length_weights``): neighbour j of vertex i gets weight
      ``|x_j - x_i|``, Alexa's measure against fold-overs: long (stretched) edges pull harder than
      short ones, so crowded, folded regions spread out instead of being pulled further together.
      With uniform weights the iteration is the plain "barycentric" relaxation.
    * **Damping** (``step``): ``x_i <- x_i + step (c_i - x_i)`` with c_i the weighted centroid;
      with edge-length weights the undamped (``step=1``) sweep oscillates and does not converge.
    * **Against collapse**: the energy the relaxation descends is smallest when all vertices meet in
      one point, and the plain iteration drifts there from any slightly asymmetric start. Alexa holds
      some vertices fixed; ``anchors`` does that (indices of vertices kept at their start
      positions). By default we instead subtract the vertices' mean before each projection
      (``recentre``), which removes the drift of the whole point set toward one side of the sphere
      without pinning any vertex (pinned vertices bias the result toward the start and can force
      fold-overs next to them). Anchors and re-centring are exclusive: re-centring would move anchors.
    * Sweeps are Jacobi (all vertices at once, with one sparse matrix product), not Gauss-Seidel.

    The exact constants of the 2000 paper could not be checked here; the weights, damping and
    collapse guard above follow the method as it is usually described (edge-length-weighted
    neighbour averaging with projection, fixed vertices against collapse). Convergence is not
    guaranteed and a converged result need not be valid, so the result carries its certificate.

    Parameters
    ----------
    vertices : (n, 3) float array
    faces : (t, 3) int array
        A closed genus-0 triangle mesh with outward (counter-clockwise) faces.
    max_iter : int
        Maximum number of sweeps.
    tol : float
        Convergence threshold on the largest vertex move of a sweep.
    step : float
        Damping factor in (0, 1].
    start : {"central", "normals"} or (n, 3) array
        Initial sphere positions (an array is normalised onto the sphere).
    edge_length_weights : bool
        Weight neighbours by edge length (True) or uniformly (False).
    recentre : bool
        Subtract the vertices' mean before projecting, against collapse. Ignored with ``anchors``.
    anchors : array of int, optional
        Vertices held at their start positions, Alexa's guard against collapse.

    Returns
    -------
    AlexaRelaxation

    Examples
    --------
    >>> from sphere_nlp.shapes import cylinder
    >>> V, F = cylinder()
    >>> result = alexa_relaxation(V, F)
    >>> result.converged, result.certificate.valid, result.iterations < 1000
    (True, True, True)
    """
    vertices = np.asarray(vertices, dtype=float)
    faces = np.asarray(faces, dtype=np.int64)
    if not 0 < step <= 1:
        raise ValueError("step must be in (0, 1]")
    n = len(vertices)
    i, j = _edges(faces).T
    rows, cols = np.r_[i, j], np.r_[j, i]
    free = np.ones(n, bool)
    if anchors is not None:
        free[np.asarray(anchors, dtype=np.int64)] = False
        recentre = False

    X = _alexa_start(vertices, faces, start)
    move = np.inf
    iterations = 0
    while iterations < max_iter and not move < tol:
        iterations += 1
        w = np.linalg.norm(X[i] - X[j], axis=1) if edge_length_weights else np.ones(len(i))
        W = sp.csr_matrix((np.r_[w, w], (rows, cols)), shape=(n, n))
        total = np.asarray(W.sum(axis=1)).ravel()
        centroid = (W @ X) / np.where(total > 0, total, 1.0)[:, None]
        Y = X + step * (centroid - X)
        if recentre:
            Y -= Y.mean(axis=0)
        Y[~free] = X[~free]
        norms = np.linalg.norm(Y, axis=1, keepdims=True)
        if not (norms > 0).all():      # a vertex reached the centre: the projection is undefined
            break
        Y /= norms
        move = float(np.max(np.linalg.norm(Y - X, axis=1)))
        X = Y
    return AlexaRelaxation(positions=X, iterations=iterations, converged=bool(move < tol),
                           last_move=move, certificate=certify(X, faces))


# --- Kazhdan, Solomon & Ben-Chen (2012) ----------------------------------------------------------------

def _normalise_surface(X, faces):
    """Translate the area-weighted centroid to the origin and scale the total area to 4 pi."""
    return (X - area_weighted_centroid(X, faces)) * np.sqrt(4 * np.pi / triangle_areas(X, faces).sum())


def cmcf_map(vertices, faces, steps=20, time_step=1.0):
    """Conformalized mean curvature flow (Kazhdan, Solomon & Ben-Chen 2012), then central projection.

    "Can mean-curvature flow be modified to be non-singular?", Computer Graphics Forum 31(5). Each
    implicit step solves ``(M_t + dt K_0) x_{t+1} = M_t x_t``, where K_0 is the cotangent Laplacian of
    the *original* mesh (the paper's modification: only the mass matrix M_t, here lumped, follows the
    flow, which removes the singularities of plain mean curvature flow and makes the flow conformal).
    After every step the surface is recentred and rescaled to area 4 pi (the flow shrinks it), so
    ``time_step`` is in units of a unit sphere. A genus-0 surface flows toward a round sphere; the
    result is the central projection of the flowed vertices from their area-weighted centroid.

    Parameters
    ----------
    vertices : (n, 3) float array
    faces : (t, 3) int array
    steps : int
        Number of implicit steps.
    time_step : float
        Step size, relative to a surface of area 4 pi.

    Returns
    -------
    (n, 3) float array of unit vectors.

    Examples
    --------
    >>> from sphere_nlp.shapes import cylinder
    >>> from sphere_nlp.certify import certify
    >>> V, F = cylinder()
    >>> certify(cmcf_map(V, F), F).valid
    True
    """
    faces = np.asarray(faces, dtype=np.int64)
    X = _normalise_surface(np.asarray(vertices, dtype=float), faces)
    stiffness = cotan_laplacian(X, faces)
    for _ in range(steps):
        mass = lumped_mass(X, faces)
        with np.errstate(divide="ignore", invalid="ignore"):
            X = sparse_lu.solve(mass + time_step * stiffness, mass @ X)
            X = _normalise_surface(X, faces)
        if not np.isfinite(X).all():
            break
    with np.errstate(divide="ignore", invalid="ignore"):
        return X / np.linalg.norm(X, axis=1, keepdims=True)


# --- the convex embedding -----------------------------------------------------------------------------

def tutte_projection(vertices, faces):
    """Tutte embedding lifted to a convex polytope and projected centrally (valid by construction).

    :func:`sphere_nlp.embedding.convex_embedding` with cotangent weights: the feasible start of
    sphere_nlp's solve, as the simplest baseline. Valid in exact arithmetic; on long-limbed meshes
    triangles can shrink below floating-point resolution, which the certificate reports.

    Examples
    --------
    >>> from sphere_nlp.shapes import cylinder
    >>> from sphere_nlp.certify import certify
    >>> V, F = cylinder()
    >>> certify(tutte_projection(V, F), F).valid
    True
    """
    from .connectivity import build_connectivity
    from .embedding import convex_embedding

    vertices = np.asarray(vertices, dtype=float)
    faces = np.asarray(faces, dtype=np.int64)
    return convex_embedding(build_connectivity(faces, len(vertices)), vertices)
