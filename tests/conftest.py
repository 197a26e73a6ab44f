from pathlib import Path

import pytest

SHARED_MESHES = Path(__file__).resolve().parents[1].parent / "shared" / "meshes"
MODELS = Path(__file__).resolve().parents[1] / "models"


def shared_mesh(name):
    """Path of a mesh in ../shared/meshes, or skip the test when the folder is absent."""
    path = SHARED_MESHES / name
    if not path.is_file():
        pytest.skip("shared mesh %s not available" % name)
    return path


def small_log_chord_problem():
    """Connectivity, log-chord NLP (original angles) and its feasible start on a small ellipsoid.

    The three redundant vertex sums are left out, as solve_angles does (with every constraint the
    Jacobian is singular at the solution, and IPOPT's result from a perturbed start then depends
    on the linear solver's ordering: objective 38.6 with METIS, an error with AMD, against 3.17).
    """
    from meshgen import ellipsoid
    from sphere_nlp import solve, starts
    from sphere_nlp.connectivity import build_connectivity
    from sphere_nlp.nlp import AngleNLP
    from sphere_nlp.targets import make_targets

    V, F = ellipsoid(1)
    c = build_connectivity(F, len(V))
    targets = make_targets("original-angles", V, F, c.vertex_degree)
    angles, excess, positions, _ = starts.feasible_start(c, V)
    nlp = AngleNLP(c, targets, dropped_vertices=solve.independent_vertices(positions))
    return c, nlp, nlp.pack(angles, excess)
