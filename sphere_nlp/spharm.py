"""SPHARM: a shape's spherical-harmonic coefficients from its sphere map, and the reconstruction.

The map makes the shape a function x(p) of the sphere point p; its coefficients up to degree L in
the real orthonormal spherical harmonics are fitted by least squares to the shape sampled (through
the map) at a dense icosphere. As in medical shape analysis (Brechbühler, Gerig & Kübler 1995), the
map should preserve area (``--target original-areas``), so that the sampling, and
the truncation error, spread evenly over the surface.
"""

import numpy as np
from scipy.special import gammaln, lpmv

from .resample import resample_at
from .shapes import icosphere


def real_harmonics(points, degree):
    """Real orthonormal spherical harmonics up to ``degree`` at unit ``points``: (m, (degree+1)**2).

    Column ``l*l + l + m`` is Y_lm, m = -l..l (cos(m phi) for m > 0, sin(|m| phi) for m < 0).

    Example
    -------
    >>> from sphere_nlp.shapes import icosphere
    >>> P = icosphere(5)[0]
    >>> Y = real_harmonics(P, 3)
    >>> float(np.abs(Y.T @ Y * 4 * np.pi / len(P) - np.eye(16)).max()) < 0.05   # equal-weight quadrature
    True
    >>> bool(np.allclose(Y[:, 3], np.sqrt(3 / (4 * np.pi)) * P[:, 0]))
    True
    """
    P = np.asarray(points, float)
    P = P / np.linalg.norm(P, axis=1, keepdims=True)
    z = np.clip(P[:, 2], -1, 1)
    phi = np.arctan2(P[:, 1], P[:, 0])
    Y = np.empty((len(P), (degree + 1) ** 2))
    for l in range(degree + 1):
        for m in range(l + 1):
            norm = np.sqrt((2 * l + 1) / (4 * np.pi) * np.exp(gammaln(l - m + 1) - gammaln(l + m + 1)))
            legendre = (-1) ** m * norm * lpmv(m, l, z)      # without the Condon-Shortley phase
            if m == 0:
                Y[:, l * l + l] = legendre
            else:
                Y[:, l * l + l + m] = np.sqrt(2) * legendre * np.cos(m * phi)
                Y[:, l * l + l - m] = np.sqrt(2) * legendre * np.sin(m * phi)
    return Y


def spharm_coefficients(X, S, F, degree, level=None):
    """Coefficients ((degree+1)**2, d) of the per-vertex values ``X`` over the sphere map ``(S, F)``.

    The values are sampled at the vertices of an icosphere (``level``: by default the smallest with
    at least 4 samples per coefficient) and fitted by least squares.
    """
    if level is None:
        level = 2
        while 10 * 4 ** level + 2 < 4 * (degree + 1) ** 2:
            level += 1
        level = max(level, 5)
    points = icosphere(level)[0]
    values = resample_at(X, S, F, points)
    coefficients, *_ = np.linalg.lstsq(real_harmonics(points, degree), values, rcond=None)
    return coefficients


def spharm_reconstruct(coefficients, points):
    """The shape given by ``coefficients`` evaluated at unit ``points`` (m, 3): (m, d)."""
    degree = int(round(np.sqrt(len(coefficients)))) - 1
    return real_harmonics(points, degree) @ coefficients
