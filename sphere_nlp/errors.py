"""Exception types, one per failure category.

Every input defect raises a subclass of :class:`MeshInputError` (CLI exit status 2); a solver or
certificate failure raises :class:`SolveError` or :class:`CertificateError` (CLI exit status 1).
Messages are single lines that name the defect, suitable for printing as they are.
"""


class SphereNLPError(Exception):
    """Base class of every error sphere_nlp raises on purpose."""

    exit_status = 1


class MeshInputError(SphereNLPError, ValueError):
    """The input mesh cannot be parameterized as given (CLI exit status 2)."""

    exit_status = 2


class UnreadableMeshError(MeshInputError):
    """The file is missing, empty, truncated, of an unknown format, or not a triangle mesh.

    Polygons with more than three corners are reported here too: they are rejected, not triangulated.
    """


class FaceIndexError(MeshInputError):
    """A face refers to a vertex index that does not exist, or repeats a vertex."""


class NonFiniteCoordinatesError(MeshInputError):
    """A vertex coordinate is NaN or infinite."""


class DegenerateFaceError(MeshInputError):
    """A face has zero area (collinear or coincident corners), so it has no angles to aim for.

    The limit is a smallest 3D corner angle of 1e-10 rad (``connectivity.DEGENERATE_ANGLE``); thin but
    real slivers are accepted.
    """


class OpenBoundaryError(MeshInputError):
    """Some edges belong to a single face: the surface has holes."""


class NonManifoldEdgeError(MeshInputError):
    """Some edges belong to three or more faces."""


class NonManifoldVertexError(MeshInputError):
    """Some vertices are pinched: their incident faces form more than one fan."""


class OrientationError(MeshInputError):
    """The faces cannot be oriented consistently (a non-orientable surface)."""


class ComponentsError(MeshInputError):
    """The mesh has more than one connected component."""


class GenusError(MeshInputError):
    """The surface is closed but not a topological sphere (genus != 0)."""


class UsageError(MeshInputError):
    """Invalid options or arguments (CLI exit status 2)."""


class SolveError(SphereNLPError):
    """IPOPT did not reach a solution (or hit an iteration or time limit).

    ``result`` holds the partial :class:`~sphere_nlp.api.SphericalParameterization`, if any.
    """

    def __init__(self, message, result=None):
        super().__init__(message)
        self.result = result


class CertificateError(SphereNLPError):
    """The sphere positions failed the certificate (norms, flips or degree).

    ``result`` holds the uncertified :class:`~sphere_nlp.api.SphericalParameterization`.
    """

    def __init__(self, message, result=None):
        super().__init__(message)
        self.result = result
