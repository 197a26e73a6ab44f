"""Small closed genus-0 meshes made by code: test cases and the shipped ``models/``.

Every function returns ``(vertices, faces)`` as numpy arrays with outward-facing,
counter-clockwise faces.
"""

import numpy as np


def tetrahedron():
    """Regular tetrahedron inscribed in the unit sphere.

    Examples
    --------
    >>> V, F = tetrahedron()
    >>> V.shape, F.shape
    ((4, 3), (4, 3))
    """
    V = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], float) / np.sqrt(3)
    F = np.array([[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]])
    return V, F


def octahedron():
    """Regular octahedron with vertices on the coordinate axes.

    Examples
    --------
    >>> V, F = octahedron()
    >>> len(V), len(F)
    (6, 8)
    """
    V = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)
    F = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4],
                  [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
    return V, F


def icosphere(subdivisions=2):
    """Unit icosphere: an icosahedron split ``subdivisions`` times (10 * 4**s + 2 vertices).

    Examples
    --------
    >>> V, F = icosphere(1)
    >>> len(V), len(F)
    (42, 80)
    """
    p = (1 + 5 ** 0.5) / 2
    V = np.array([[-1, p, 0], [1, p, 0], [-1, -p, 0], [1, -p, 0], [0, -1, p], [0, 1, p],
                  [0, -1, -p], [0, 1, -p], [p, 0, -1], [p, 0, 1], [-p, 0, -1], [-p, 0, 1]], float)
    F = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9],
                  [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2],
                  [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10],
                  [8, 6, 7], [9, 8, 1]])
    V /= np.linalg.norm(V, axis=1, keepdims=True)
    for _ in range(subdivisions):
        V, F = _split_triangles(V, F)
        V /= np.linalg.norm(V, axis=1, keepdims=True)
    return V, F


def _split_triangles(V, F):
    """One 1-to-4 midpoint split; shared edge midpoints are created once."""
    edges = np.sort(np.concatenate([F[:, [1, 2]], F[:, [2, 0]], F[:, [0, 1]]]), axis=1)
    unique, inverse = np.unique(edges, axis=0, return_inverse=True)
    mid = len(V) + inverse.reshape(3, -1).T  # mid[:, j] = midpoint of the edge opposite corner j
    V = np.vstack([V, V[unique].mean(axis=1)])
    a, b, c = F.T
    ma, mb, mc = mid.T
    F = np.vstack([np.c_[a, mc, mb], np.c_[b, ma, mc], np.c_[c, mb, ma], np.c_[ma, mb, mc]])
    return V, F


def cylinder(segments=12, rings=6, radius=1.0, height=2.0):
    """Closed cylinder like Fig. 3a of Sheffer, Gotsman & Dyn (2004).

    The side is a grid of ``segments`` x ``rings`` rectangles, each split by a diagonal into two right
    triangles; each cap is a fan around a centre vertex.

    Parameters
    ----------
    segments : int
        Vertices around each ring (>= 3).
    rings : int
        Rectangles along the height (>= 1); there are ``rings + 1`` rings of vertices.
    radius, height : float
        Size of the cylinder, whose axis is z and which is centred on the origin.

    Returns
    -------
    vertices : (segments * (rings + 1) + 2, 3) float array
        Ring vertices first (bottom ring first), then the bottom and top cap centres.
    faces : (2 * segments * (rings + 1), 3) int array
        Side triangles first (two per rectangle), then the bottom fan, then the top fan.

    Examples
    --------
    >>> V, F = cylinder(12, 6)
    >>> len(V) - 3 * len(F) // 2 + len(F)   # Euler characteristic
    2
    """
    if segments < 3 or rings < 1:
        raise ValueError("cylinder needs segments >= 3 and rings >= 1")
    theta = 2 * np.pi * np.arange(segments) / segments
    z = np.linspace(-height / 2, height / 2, rings + 1)
    ring = np.c_[radius * np.cos(theta), radius * np.sin(theta)]
    V = np.vstack([np.c_[ring, np.full(segments, zk)] for zk in z]
                  + [[[0, 0, -height / 2], [0, 0, height / 2]]])
    k = np.arange(segments)
    faces = []
    for r in range(rings):
        a = r * segments + k                      # this ring
        b = r * segments + (k + 1) % segments     # this ring, next around
        c, d = a + segments, b + segments         # the ring above
        faces += [np.c_[a, b, d], np.c_[a, d, c]]
    bottom, top = len(V) - 2, len(V) - 1
    last = rings * segments
    faces += [np.c_[np.full(segments, bottom), (k + 1) % segments, k],
              np.c_[np.full(segments, top), last + k, last + (k + 1) % segments]]
    return V, np.vstack(faces)


def write_models(directory):
    """Regenerate the meshes shipped in ``models/`` (run ``python -m sphere_nlp.shapes models``)."""
    from pathlib import Path

    from .mesh_io import write_mesh

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    write_mesh(directory / "cylinder.off", *cylinder())


if __name__ == "__main__":
    import sys

    write_models(sys.argv[1] if len(sys.argv) > 1 else "models")
