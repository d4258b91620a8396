"""The world: the hidden surface, geodesics and rods, sensing and motion, ground truth, results.

Only this package knows the surface and absolute positions; ``agents`` never imports it.
"""
from world.geometry import ideal_formation

__all__ = ["ideal_formation"]
