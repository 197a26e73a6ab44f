"""Point location on a sphere mesh: the spherical triangle holding each query direction, with barycentrics.

Candidates come from a KD-tree (:class:`scipy.spatial.cKDTree`) over the triangles' normalised
centroids; each candidate gets an exact inside test by central (gnomonic) projection: a unit vector
``q`` lies in the spherical triangle ``(a, b, c)`` exactly when ``q = la a + lb b + lc c`` with all
``l >= 0``, and ``l / sum(l)`` are the planar barycentrics of the point where the ray through ``q``
meets the triangle's plane. Queries not found among the nearest candidates are retried with a wider
candidate set, and the last few against every triangle, so every query gets a triangle.
"""

import numpy as np
from scipy.spatial import cKDTree

from .geometry import cross

# Inside test tolerance on the normalised coefficients: a query on an edge belongs to both triangles.
INSIDE_TOLERANCE = 1e-12


def _unit(points):
    points = np.asarray(points, float)
    return points / np.linalg.norm(points, axis=-1, keepdims=True)


def _coefficients(queries, triangles):
    """Solve ``q = la a + lb b + lc c`` for each (query, triangle) pair; rows normalised to sum 1.

    Returns the normalised coefficients (m, 3) and the sum before normalising (positive when the
    query is on the triangle's side of the origin).
    """
    a, b, c = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    la = np.einsum("ij,ij->i", queries, cross(b, c))
    lb = np.einsum("ij,ij->i", queries, cross(c, a))
    lc = np.einsum("ij,ij->i", queries, cross(a, b))
    lam = np.stack([la, lb, lc], axis=1)
    total = lam.sum(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        return lam / total[:, None], total


class SphereLocator:
    """Locate unit vectors in the spherical triangles of a (certified) sphere mesh.

    Parameters
    ----------
    vertices : (n, 3) array
        Positions on the unit sphere (normalised again here).
    faces : (t, 3) int array
        Triangles, consistently oriented outward, covering the sphere once (a certified map).

    Examples
    --------
    >>> from sphere_nlp.shapes import icosphere
    >>> V, F = icosphere(2)
    >>> faces, bary = SphereLocator(V, F).locate([[0.0, 0.6, 0.8], [1.0, 0.0, 0.0]])
    >>> bool(np.allclose(bary.sum(axis=1), 1)), bool((bary >= 0).all())
    (True, True)
    >>> q = np.einsum("ij,ijk->ik", bary, V[F[faces]])
    >>> np.round(q / np.linalg.norm(q, axis=1, keepdims=True), 12).tolist()
    [[0.0, 0.6, 0.8], [1.0, 0.0, 0.0]]
    """

    def __init__(self, vertices, faces):
        self.vertices = _unit(vertices)
        self.faces = np.asarray(faces, np.int64)
        self.triangles = self.vertices[self.faces]
        self.tree = cKDTree(_unit(self.triangles.sum(axis=1)))

    def locate(self, queries, k=(8, 32, 128)):
        """Triangle index (m,) and barycentric coordinates (m, 3) of each query direction.

        Barycentrics are the gnomonic ones: non-negative, summing to 1, and
        ``normalise(bary @ vertices[faces[face]])`` is the query. ``k`` are the growing numbers of
        nearest triangle centroids tried; queries still not found are tested against all triangles.
        """
        queries = _unit(np.atleast_2d(queries))
        m = len(queries)
        found_face = np.full(m, -1, np.int64)
        found_bary = np.zeros((m, 3))
        todo = np.arange(m)
        t = len(self.faces)
        for kk in k:
            if not len(todo):
                break
            kk = min(kk, t)
            _, cand = self.tree.query(queries[todo], k=kk)
            cand = cand.reshape(len(todo), kk)
            self._test(queries, todo, cand, found_face, found_bary)
            todo = todo[found_face[todo] < 0]
        for chunk in np.array_split(todo, max(1, len(todo) * t // 4_000_000 + 1)) if len(todo) else []:
            # The last resort: every triangle; the best (largest smallest coefficient) wins, so a query
            # is placed even if round-off put it a hair outside every triangle.
            q = np.repeat(queries[chunk], t, axis=0)
            lam, total = _coefficients(q, np.tile(self.triangles, (len(chunk), 1, 1)))
            score = np.where(total > 0, lam.min(axis=1), -np.inf).reshape(len(chunk), t)
            best = score.argmax(axis=1)
            found_face[chunk] = best
            found_bary[chunk] = lam.reshape(len(chunk), t, 3)[np.arange(len(chunk)), best]
        found_bary = np.clip(found_bary, 0.0, None)
        found_bary /= found_bary.sum(axis=1, keepdims=True)
        return found_face, found_bary

    def _test(self, queries, rows, cand, found_face, found_bary):
        kk = cand.shape[1]
        q = np.repeat(queries[rows], kk, axis=0)
        lam, total = _coefficients(q, self.triangles[cand.ravel()])
        inside = ((total > 0) & (lam.min(axis=1) >= -INSIDE_TOLERANCE)).reshape(len(rows), kk)
        hit = inside.any(axis=1)
        first = inside.argmax(axis=1)
        sel = rows[hit]
        found_face[sel] = cand[hit, first[hit]]
        found_bary[sel] = lam.reshape(len(rows), kk, 3)[hit, first[hit]]


def interpolate(values, faces, face_index, bary):
    """Barycentric interpolation of per-vertex ``values`` (n,) or (n, d) at located points."""
    values = np.asarray(values)
    corner = values[np.asarray(faces)[face_index]]           # (m, 3) or (m, 3, d)
    if corner.ndim == 2:
        return np.einsum("ij,ij->i", bary, corner)
    return np.einsum("ij,ijk->ik", bary, corner)


def nearest_corner(values, faces, face_index, bary):
    """Per-vertex ``values`` of the located triangle's corner with the largest weight (for labels)."""
    corner = np.asarray(faces)[face_index, np.argmax(bary, axis=1)]
    return np.asarray(values)[corner]
