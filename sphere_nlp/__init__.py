"""sphere_nlp: robust spherical parameterization of closed genus-0 triangle meshes.

An implementation of Sheffer, Gotsman & Dyn, "Robust Spherical Parameterization of Triangular
Meshes", Computing 72 (2004), as a CasADi NLP solved by IPOPT.

>>> import sphere_nlp
>>> from sphere_nlp.shapes import octahedron
>>> result = sphere_nlp.parameterize(octahedron(), target="equal-angles")
>>> result.certificate.valid
True

The names below load their modules (numpy, CasADi, ...) on first use, so that importing the
package is instant: the command line takes over SIGINT / SIGTERM before anything heavy loads
(:func:`sphere_nlp.interrupts.program_started`).
"""

import importlib

from .errors import (CertificateError, ComponentsError, DegenerateFaceError, FaceIndexError, GenusError,
                     MeshInputError, NonFiniteCoordinatesError, NonManifoldEdgeError,
                     NonManifoldVertexError, OpenBoundaryError, OrientationError, SolveError,
                     SphereNLPError, UnreadableMeshError, UsageError)

__version__ = "0.1.0"

# Public name: the module that defines it.
_LAZY = {"parameterize": "api", "SphericalParameterization": "api", "certify": "certify",
         "Certificate": "certify", "load_mesh": "mesh_io", "write_mesh": "mesh_io",
         "SolverSettings": "settings", "MODES": "targets"}

__all__ = [
    "parameterize", "SphericalParameterization", "certify", "Certificate", "load_mesh", "write_mesh",
    "MODES", "SphereNLPError", "MeshInputError", "UnreadableMeshError", "FaceIndexError",
    "NonFiniteCoordinatesError", "DegenerateFaceError", "OpenBoundaryError", "NonManifoldEdgeError",
    "NonManifoldVertexError", "OrientationError", "ComponentsError", "GenusError", "UsageError",
    "SolveError", "CertificateError", "SolverSettings",
]


def __getattr__(name):
    if name in _LAZY:
        value = getattr(importlib.import_module("." + _LAZY[name], __name__), name)
        globals()[name] = value
        return value
    try:                                  # a submodule, e.g. sphere_nlp.api after `import sphere_nlp`
        return importlib.import_module("." + name, __name__)
    except ModuleNotFoundError as exc:
        if exc.name != "%s.%s" % (__name__, name):
            raise
        raise AttributeError("module %r has no attribute %r" % (__name__, name)) from None


def __dir__():
    return sorted(set(globals()) | set(_LAZY))
