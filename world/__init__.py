"""The world: the hidden surface, geodesics and rods, sensing and motion, ground truth, results.

Only this package knows the surface and absolute positions; ``agents`` never imports it.
"""
import protocol  # noqa: F401  (first: one BLAS thread per process, see protocol/__init__)
from world.geometry import ideal_formation

__all__ = ["ideal_formation"]
