"""Carry a spherical map of a mesh over to its 1-to-4 subdivision (the paper's mesh hierarchy).

Solving a subdivided mesh from its coarse parent's solution skips most of the way the area modes
walk from the conformal start to their targets, and starts their main stage nearer an optimum
(``benchmarks/run.py --loop-from-coarse`` measures it on the Loop-subdivided armadillo). Not
necessarily the conformal start's: the area modes' objective has many local optima, and bunny's
Loop subdivision solved from bunny's map ended at objective 120.6 in 100 iterations, against 107.8
in 278 from its conformal start (docs/design.md, "Where the area modes' iterations go").
"""

import numpy as np
import scipy.sparse as sp


def prolong_to_subdivision(coarse_positions, fine_faces):
    """Unit-sphere positions for a 1-to-4 subdivision of a mesh, from a spherical map of the mesh.

    The subdivision must number the coarse vertices first, as Loop and midpoint subdivision do
    (``trimesh.remesh.subdivide_loop``, ``trimesh.remesh.subdivide``); each other vertex splits one
    coarse edge, so its coarse neighbours are that edge's two ends. It is placed at the edge's
    geodesic midpoint, which splits every spherical triangle of a valid map into four valid ones.

    Parameters
    ----------
    coarse_positions : (n_coarse, 3) array
        Unit vectors, a valid spherical map of the coarse mesh.
    fine_faces : (4 t, 3) int array
        Triangles of the subdivided mesh.

    Returns
    -------
    (n_fine, 3) array of unit vectors, for ``parameterize(..., start=...)``.

    Raises
    ------
    ValueError
        If a new vertex does not have exactly two coarse neighbours (not a 1-to-4 subdivision
        numbered coarse-first).

    Examples
    --------
    >>> import trimesh
    >>> from sphere_nlp.certify import certify
    >>> from sphere_nlp.shapes import octahedron
    >>> V, F = octahedron()
    >>> fine_V, fine_F = trimesh.remesh.subdivide_loop(V, F, iterations=1)
    >>> X = prolong_to_subdivision(V / np.linalg.norm(V, axis=1, keepdims=True), fine_F)
    >>> X.shape, certify(X, fine_F).valid
    ((18, 3), True)
    """
    coarse_positions = np.asarray(coarse_positions, dtype=float)
    fine_faces = np.asarray(fine_faces)
    n_coarse = len(coarse_positions)
    n_fine = int(fine_faces.max()) + 1
    a = fine_faces.ravel()
    b = np.roll(fine_faces, -1, axis=1).ravel()
    adjacency = sp.coo_matrix((np.ones(len(a)), (a, b)), shape=(n_fine, n_fine)).tocsr()
    adjacency = ((adjacency + adjacency.T) > 0).tocsr()
    # Each new vertex's links to coarse vertices: exactly its edge's two ends.
    to_coarse = adjacency[n_coarse:, :n_coarse].tocsr()
    counts = np.diff(to_coarse.indptr)
    if len(counts) and (counts != 2).any():
        bad = n_coarse + int(np.flatnonzero(counts != 2)[0])
        raise ValueError("vertex %d has %d coarse neighbours, not 2: not a 1-to-4 subdivision numbered "
                         "coarse vertices first" % (bad, counts[bad - n_coarse]))
    ends = to_coarse.indices.reshape(-1, 2)
    midpoints = coarse_positions[ends[:, 0]] + coarse_positions[ends[:, 1]]
    midpoints /= np.linalg.norm(midpoints, axis=1, keepdims=True)
    return np.vstack([coarse_positions, midpoints])
