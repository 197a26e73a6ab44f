"""sphere_nlp: robust spherical parameterization of closed genus-0 triangle meshes.

An implementation of Sheffer, Gotsman & Dyn, "Robust Spherical Parameterization of Triangular
Meshes", Computing 72 (2004), as a CasADi NLP solved by IPOPT.

>>> import sphere_nlp
>>> from sphere_nlp.shapes import octahedron
>>> result = sphere_nlp.parameterize(octahedron(), target="equal-angles")
>>> result.certificate.valid
True
"""

from .api import SphericalParameterization, parameterize
from .certify import Certificate, certify
from .errors import (CertificateError, ComponentsError, DegenerateFaceError, FaceIndexError, GenusError,
                     MeshInputError, NonFiniteCoordinatesError, NonManifoldEdgeError,
                     NonManifoldVertexError, OpenBoundaryError, OrientationError, SolveError,
                     SphereNLPError, UnreadableMeshError, UsageError)
from .mesh_io import load_mesh, write_mesh
from .settings import SolverSettings
from .targets import MODES

__version__ = "0.1.0"

__all__ = [
    "parameterize", "SphericalParameterization", "certify", "Certificate", "load_mesh", "write_mesh",
    "MODES", "SphereNLPError", "MeshInputError", "UnreadableMeshError", "FaceIndexError",
    "NonFiniteCoordinatesError", "DegenerateFaceError", "OpenBoundaryError", "NonManifoldEdgeError",
    "NonManifoldVertexError", "OrientationError", "ComponentsError", "GenusError", "UsageError",
    "SolveError", "CertificateError", "SolverSettings",
]
