"""Baseline spherical maps to compare sphere_nlp against.

:func:`alexa_relaxation` is the relaxation of Alexa (2000), the method of panel (b) of the paper's Fig. 3.
"""

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from .certify import Certificate, certify
from .targets import triangle_areas_3d

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


def _start_positions(vertices, faces, start):
    """Initial sphere positions: central projection from the centroid, or the Gauss map of normals."""
    if not isinstance(start, str):
        positions = np.array(start, dtype=float)
        if positions.shape != vertices.shape:
            raise ValueError("start positions must have shape %s" % (vertices.shape,))
    elif start == "central":
        # The area-weighted surface centroid, so dense regions of the mesh do not pull the centre.
        areas = triangle_areas_3d(vertices, faces)
        centre = (areas[:, None] * vertices[faces].mean(axis=1)).sum(axis=0) / areas.sum()
        positions = vertices - centre
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

    X = _start_positions(vertices, faces, start)
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
