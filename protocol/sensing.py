"""The declared range/bearing sensor model (design §5), shared by the world, which applies it,
and the agents, which know their sensor's datasheet but never its draws.

A reading of a point at range ``r`` and bearing ``theta`` carries independent Gaussian noise
of standard deviations ``sigma_r`` (length) and ``sigma_theta`` (radians) on the two; in xy
that is, to first order, a covariance stretched along the line of sight by ``sigma_r`` and
across it by ``r * sigma_theta``: bearing noise grows with distance, range noise does not.
"""
from __future__ import annotations

import math

import numpy as np


def reading_covariance(r: float, theta: float, sigma_r: float,
                       sigma_theta: float) -> np.ndarray:
    """Covariance (2, 2) of the xy reading of a point at ``(r, theta)`` (first order).

    >>> reading_covariance(2.0, 0.0, 0.1, 0.05).round(12)
    array([[0.01, 0.  ],
           [0.  , 0.01]])
    """
    c, s = math.cos(theta), math.sin(theta)
    jacobian = np.array([[c, -r * s], [s, r * c]])
    return jacobian @ np.diag([sigma_r**2, sigma_theta**2]) @ jacobian.T


def reading_variance(distance: float, sigma_r: float, sigma_theta: float) -> float:
    """The same reading's variance per xy coordinate (half the covariance's trace):
    ``(sigma_r**2 + (distance * sigma_theta)**2) / 2``.

    >>> reading_variance(3.0, 0.02, 0.01)
    0.00065
    """
    return (sigma_r**2 + (distance * sigma_theta) ** 2) / 2.0

