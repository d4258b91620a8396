"""Surfaces ``z = F(x, y)`` the column drives over: the protocol, the presets, and a loader.

A surface is any object with ``height``, ``gradient`` and ``hessian`` at a point ``p = (x, y)``
(design §3), optionally with ``contains(p)`` telling whether ``p`` lies in its domain (no
``contains`` means the whole plane). The presets below implement these methods in numpy and
also carry an integer ``kind`` and a float64 ``params`` array, which
:func:`preset_derivatives`, a numba kernel, turns into the same derivatives for the fast
geodesic integrator of :mod:`world.geometry`.

Presets (``name``: ``F(x, y)``, keyword parameters with defaults, passed to the class or
through :func:`make_surface`):

- ``elliptic``: ``(x² + y²)/30``
- ``hyperbolic``: ``(x² − y²)/30``
- ``wavy``: ``sin(x/3) + cos(y/3)``
- ``plane``: ``a·x + b·y``; ``a = 0.3``, ``b = −0.2``
- ``gaussian-hill`` (held out): ``A·exp(−((x − x0)² + (y − y0)²)/(2σ²))``;
  ``amplitude = 6``, ``sigma = 8``, ``x0 = 0``, ``y0 = 0``
- ``ripple`` (held out): ``A·sin(k·sqrt(x² + y² + ε))``; ``amplitude = 1.5``,
  ``wavenumber = 0.25``, ``epsilon = 1``
- ``hemisphere``: ``sqrt(R² − x² − y²)`` on the open disc ``x² + y² < R²``; ``radius = 20``

Real terrain: ``dem:PATH`` loads a digital elevation model (:mod:`world.dem`; parameter
``smoothing = 0``).
"""
from __future__ import annotations

import dataclasses
import math
import numbers
from collections.abc import Mapping
from dataclasses import dataclass
from functools import cached_property
from typing import Any, ClassVar, Protocol, runtime_checkable

import numba
import numpy as np
from numpy.typing import ArrayLike

from protocol.distribution import require
from protocol.imports import import_user_module

LeaderStart = tuple[float, float, float, float]
DEM_PREFIX = "dem:"  # a surface name "dem:PATH" is a digital elevation model (world.dem)


def require_surface_extra(name: str) -> None:
    """Refuse (:class:`protocol.distribution.MissingExtra`) a surface whose loading needs an
    extra that is not installed — a DEM without ``[dem]`` — before anything is written."""
    if name.startswith(DEM_PREFIX):
        require("dem")


@runtime_checkable
class Surface(Protocol):
    """A height field ``z = F(x, y)``; ``p`` is a point ``(x, y)``, shape (2,).

    An implementation may also define ``contains(p) -> bool`` (its domain) and a
    ``default_leader_start`` ``(x, y, vx, vy)``; neither is required.
    """

    def height(self, p: ArrayLike) -> float:
        """Return ``F(p)``."""

    def gradient(self, p: ArrayLike) -> np.ndarray:
        """Return ``(Fx, Fy)`` at ``p``, shape (2,)."""

    def hessian(self, p: ArrayLike) -> np.ndarray:
        """Return ``[[Fxx, Fxy], [Fxy, Fyy]]`` at ``p``, shape (2, 2)."""


def _xy(p: ArrayLike) -> tuple[float, float]:
    """Split a point into two floats, rejecting anything that is not a finite (2,) vector."""
    point = np.asarray(p, dtype=float)
    if point.shape != (2,) or not np.all(np.isfinite(point)):
        raise ValueError(f"p must be a finite point (x, y) of shape (2,), got {p!r}")
    return float(point[0]), float(point[1])


def _hessian(fxx: float, fxy: float, fyy: float) -> np.ndarray:
    return np.array([[fxx, fxy], [fxy, fyy]])


class PresetSurface:
    """Shared behaviour of the preset dataclasses: parameter checks and the kernel inputs.

    Subclasses are frozen dataclasses whose fields are their parameters, in the order the
    kernel reads them from :attr:`params`.
    """

    name: ClassVar[str]
    kind: ClassVar[int]
    default_leader_start: ClassVar[LeaderStart]
    _positive: ClassVar[tuple[str, ...]] = ()

    def __post_init__(self) -> None:
        for spec in dataclasses.fields(self):
            value = getattr(self, spec.name)
            if isinstance(value, bool) or not isinstance(value, numbers.Real):
                raise ValueError(f"{spec.name} must be a real number, got {value!r}")
            if not math.isfinite(value):
                raise ValueError(f"{spec.name} must be finite, got {value!r}")
            if spec.name in self._positive and value <= 0:
                raise ValueError(f"{spec.name} must be > 0, got {value!r}")
            object.__setattr__(self, spec.name, float(value))

    @cached_property
    def params(self) -> np.ndarray:
        """The parameters in field order, read-only float64, shape (n_params,)."""
        values = np.array([getattr(self, spec.name) for spec in dataclasses.fields(self)],
                          dtype=np.float64)
        values.flags.writeable = False
        return values


@dataclass(frozen=True)
class Elliptic(PresetSurface):
    """Type I (elliptic) paraboloid ``F = (x² + y²)/30``."""

    name: ClassVar[str] = "elliptic"
    kind: ClassVar[int] = 0
    default_leader_start: ClassVar[LeaderStart] = (
        50.0, -10.0, -math.cos(math.pi / 36), math.sin(math.pi / 36))

    def height(self, p: ArrayLike) -> float:
        x, y = _xy(p)
        return (x * x + y * y) / 30.0

    def gradient(self, p: ArrayLike) -> np.ndarray:
        x, y = _xy(p)
        return np.array([x / 15.0, y / 15.0])

    def hessian(self, p: ArrayLike) -> np.ndarray:
        _xy(p)
        return _hessian(1.0 / 15.0, 0.0, 1.0 / 15.0)


@dataclass(frozen=True)
class Hyperbolic(PresetSurface):
    """Type II (hyperbolic) paraboloid, a saddle, ``F = (x² − y²)/30``."""

    name: ClassVar[str] = "hyperbolic"
    kind: ClassVar[int] = 1
    default_leader_start: ClassVar[LeaderStart] = (50.0, -20.0, 1.0, 0.0)

    def height(self, p: ArrayLike) -> float:
        x, y = _xy(p)
        return (x * x - y * y) / 30.0

    def gradient(self, p: ArrayLike) -> np.ndarray:
        x, y = _xy(p)
        return np.array([x / 15.0, -y / 15.0])

    def hessian(self, p: ArrayLike) -> np.ndarray:
        _xy(p)
        return _hessian(1.0 / 15.0, 0.0, -1.0 / 15.0)


@dataclass(frozen=True)
class Wavy(PresetSurface):
    """Type III egg-crate ``F = sin(x/3) + cos(y/3)``."""

    name: ClassVar[str] = "wavy"
    kind: ClassVar[int] = 2
    default_leader_start: ClassVar[LeaderStart] = (30.0, 5.0, 1.0, 0.0)

    def height(self, p: ArrayLike) -> float:
        x, y = _xy(p)
        return math.sin(x / 3.0) + math.cos(y / 3.0)

    def gradient(self, p: ArrayLike) -> np.ndarray:
        x, y = _xy(p)
        return np.array([math.cos(x / 3.0) / 3.0, -math.sin(y / 3.0) / 3.0])

    def hessian(self, p: ArrayLike) -> np.ndarray:
        x, y = _xy(p)
        return _hessian(-math.sin(x / 3.0) / 9.0, 0.0, -math.cos(y / 3.0) / 9.0)


@dataclass(frozen=True)
class Plane(PresetSurface):
    """Tilted plane ``F = a·x + b·y``: flat metric, straight geodesics."""

    name: ClassVar[str] = "plane"
    kind: ClassVar[int] = 3
    default_leader_start: ClassVar[LeaderStart] = (0.0, 0.0, 1.0, 0.0)
    a: float = 0.3
    b: float = -0.2

    def height(self, p: ArrayLike) -> float:
        x, y = _xy(p)
        return self.a * x + self.b * y

    def gradient(self, p: ArrayLike) -> np.ndarray:
        _xy(p)
        return np.array([self.a, self.b])

    def hessian(self, p: ArrayLike) -> np.ndarray:
        _xy(p)
        return _hessian(0.0, 0.0, 0.0)


@dataclass(frozen=True)
class GaussianHill(PresetSurface):
    """Held-out surface: one Gaussian bump ``F = A·exp(−((x−x0)² + (y−y0)²)/(2σ²))``."""

    name: ClassVar[str] = "gaussian-hill"
    kind: ClassVar[int] = 4
    default_leader_start: ClassVar[LeaderStart] = (-30.0, 6.0, 1.0, 0.0)
    _positive: ClassVar[tuple[str, ...]] = ("sigma",)
    amplitude: float = 6.0
    sigma: float = 8.0
    x0: float = 0.0
    y0: float = 0.0

    def height(self, p: ArrayLike) -> float:
        x, y = _xy(p)
        dx, dy = x - self.x0, y - self.y0
        return self.amplitude * math.exp(-(dx * dx + dy * dy) / (2.0 * self.sigma ** 2))

    def gradient(self, p: ArrayLike) -> np.ndarray:
        x, y = _xy(p)
        scale = -self.height(p) / self.sigma ** 2
        return np.array([scale * (x - self.x0), scale * (y - self.y0)])

    def hessian(self, p: ArrayLike) -> np.ndarray:
        x, y = _xy(p)
        dx, dy = x - self.x0, y - self.y0
        s2 = self.sigma ** 2
        f = self.height(p) / (s2 * s2)
        return _hessian(f * (dx * dx - s2), f * dx * dy, f * (dy * dy - s2))


@dataclass(frozen=True)
class Ripple(PresetSurface):
    """Held-out surface: radial ripple ``F = A·sin(k·ρ)``, ``ρ = sqrt(x² + y² + ε)``."""

    name: ClassVar[str] = "ripple"
    kind: ClassVar[int] = 5
    default_leader_start: ClassVar[LeaderStart] = (-30.0, 10.0, 1.0, 0.0)
    _positive: ClassVar[tuple[str, ...]] = ("epsilon",)
    amplitude: float = 1.5
    wavenumber: float = 0.25
    epsilon: float = 1.0

    def _radial(self, p: ArrayLike) -> tuple[float, float, float, float, float]:
        """Return ``x, y, ρ, G'(ρ), G''(ρ)`` with ``G(ρ) = A·sin(kρ)``."""
        x, y = _xy(p)
        rho = math.sqrt(x * x + y * y + self.epsilon)
        a, k = self.amplitude, self.wavenumber
        return x, y, rho, a * k * math.cos(k * rho), -a * k * k * math.sin(k * rho)

    def height(self, p: ArrayLike) -> float:
        x, y = _xy(p)
        return self.amplitude * math.sin(self.wavenumber * math.sqrt(x * x + y * y + self.epsilon))

    def gradient(self, p: ArrayLike) -> np.ndarray:
        x, y, rho, d1, _ = self._radial(p)
        return np.array([d1 * x / rho, d1 * y / rho])

    def hessian(self, p: ArrayLike) -> np.ndarray:
        x, y, rho, d1, d2 = self._radial(p)
        radial, tangential = d2 / (rho * rho), d1 / rho ** 3
        return _hessian(radial * x * x + tangential * (rho * rho - x * x),
                        (radial - tangential) * x * y,
                        radial * y * y + tangential * (rho * rho - y * y))


@dataclass(frozen=True)
class Hemisphere(PresetSurface):
    """Upper hemisphere ``F = sqrt(R² − x² − y²)`` on the open disc ``x² + y² < R²``.

    Its geodesics are great circles, which gives the tests analytic ground truth.
    """

    name: ClassVar[str] = "hemisphere"
    kind: ClassVar[int] = 6
    default_leader_start: ClassVar[LeaderStart] = (0.0, 0.0, 1.0, 0.0)
    _positive: ClassVar[tuple[str, ...]] = ("radius",)
    radius: float = 20.0

    def contains(self, p: ArrayLike) -> bool:
        """Whether ``p`` lies in the open disc of radius ``radius``."""
        x, y = _xy(p)
        return x * x + y * y < self.radius ** 2

    def _height_inside(self, p: ArrayLike) -> tuple[float, float, float]:
        x, y = _xy(p)
        if not self.contains((x, y)):
            raise ValueError(f"p must lie inside the hemisphere's disc of radius {self.radius}, "
                             f"got {p!r}")
        return x, y, math.sqrt(self.radius ** 2 - x * x - y * y)

    def height(self, p: ArrayLike) -> float:
        return self._height_inside(p)[2]

    def gradient(self, p: ArrayLike) -> np.ndarray:
        x, y, z = self._height_inside(p)
        return np.array([-x / z, -y / z])

    def hessian(self, p: ArrayLike) -> np.ndarray:
        x, y, z = self._height_inside(p)
        z3 = z ** 3
        return _hessian(-1.0 / z - x * x / z3, -x * y / z3, -1.0 / z - y * y / z3)


PRESETS: Mapping[str, type[PresetSurface]] = {
    cls.name: cls for cls in (Elliptic, Hyperbolic, Wavy, Plane, GaussianHill, Ripple, Hemisphere)
}


@numba.njit(cache=True)
def preset_derivatives(kind: int, params: np.ndarray, x: float,
                       y: float) -> tuple[bool, float, float, float, float, float]:
    """Derivatives of the preset surface ``kind`` (see the classes' ``kind``) at ``(x, y)``.

    Parameters
    ----------
    kind : int
        The preset's ``kind`` code.
    params : ndarray, shape (n_params,)
        The preset's ``params``.
    x, y : float
        The point.

    Returns
    -------
    inside : bool
        Whether ``(x, y)`` lies in the surface's domain (the derivatives are NaN otherwise).
    fx, fy, fxx, fxy, fyy : float
        ``∂F/∂x, ∂F/∂y, ∂²F/∂x², ∂²F/∂x∂y, ∂²F/∂y²``; NaN for an unknown ``kind``.
    """
    nan = math.nan
    if kind == 0:
        return True, x / 15.0, y / 15.0, 1.0 / 15.0, 0.0, 1.0 / 15.0
    if kind == 1:
        return True, x / 15.0, -y / 15.0, 1.0 / 15.0, 0.0, -1.0 / 15.0
    if kind == 2:
        return (True, math.cos(x / 3.0) / 3.0, -math.sin(y / 3.0) / 3.0,
                -math.sin(x / 3.0) / 9.0, 0.0, -math.cos(y / 3.0) / 9.0)
    if kind == 3:
        return True, params[0], params[1], 0.0, 0.0, 0.0
    if kind == 4:
        amplitude, sigma, dx, dy = params[0], params[1], x - params[2], y - params[3]
        s2 = sigma * sigma
        f = amplitude * math.exp(-(dx * dx + dy * dy) / (2.0 * s2))
        return (True, -f * dx / s2, -f * dy / s2, f * (dx * dx - s2) / (s2 * s2),
                f * dx * dy / (s2 * s2), f * (dy * dy - s2) / (s2 * s2))
    if kind == 5:
        amplitude, k, epsilon = params[0], params[1], params[2]
        rho2 = x * x + y * y + epsilon
        rho = math.sqrt(rho2)
        d1 = amplitude * k * math.cos(k * rho)
        d2 = -amplitude * k * k * math.sin(k * rho)
        radial, tangential = d2 / rho2, d1 / (rho2 * rho)
        return (True, d1 * x / rho, d1 * y / rho, radial * x * x + tangential * (rho2 - x * x),
                (radial - tangential) * x * y, radial * y * y + tangential * (rho2 - y * y))
    if kind == 6:
        z2 = params[0] * params[0] - x * x - y * y
        if not z2 > 0.0:
            return False, nan, nan, nan, nan, nan
        z = math.sqrt(z2)
        z3 = z2 * z
        return True, -x / z, -y / z, -1.0 / z - x * x / z3, -x * y / z3, -1.0 / z - y * y / z3
    return False, nan, nan, nan, nan, nan


def make_surface(name: str, params: Mapping[str, Any] | None = None) -> Surface:
    """Build a surface from a preset name or a ``package.module:attr`` reference.

    Parameters
    ----------
    name : str
        A key of :data:`PRESETS`, ``"dem:PATH"`` (a DEM raster, :mod:`world.dem`), or
        ``"package.module:attr"`` naming a Surface object or a zero-argument callable (e.g. a
        class) returning one. Only the world imports it.
    params : mapping of str to float, optional
        Keyword parameters of the preset (see the module table), or ``smoothing`` for a DEM.
        Not allowed with a ``module:attr`` reference.

    Returns
    -------
    Surface

    Raises
    ------
    ValueError
        Unknown preset, unknown or invalid parameters, a module that cannot be imported, a
        missing attribute, an object that is not a surface, or a DEM that cannot be used
        (see :func:`world.dem.read_dem`).
    """
    if not isinstance(name, str) or not name:
        raise ValueError(f"name must be a preset name or 'package.module:attr', got {name!r}")
    params = dict(params or {})
    if name.startswith(DEM_PREFIX):
        from world.dem import make_dem_surface

        return make_dem_surface(name, params)
    if ":" in name:
        if params:
            raise ValueError(f"params apply only to presets, not to the custom surface {name!r}")
        return _import_surface(name)
    if name not in PRESETS:
        raise ValueError(f"name {name!r} is not a preset ({', '.join(PRESETS)}) "
                         "nor a 'package.module:attr' reference")
    cls = PRESETS[name]
    known = [spec.name for spec in dataclasses.fields(cls)]
    unknown = sorted(set(params) - set(known))
    if unknown:
        raise ValueError(f"params {unknown} are not parameters of surface {name!r} "
                         f"(it takes {known or 'none'})")
    return cls(**params)


def _import_surface(reference: str) -> Surface:
    """Resolve ``"package.module:attr"`` to a surface, calling ``attr`` if it is a factory."""
    module_name, _, attr = reference.partition(":")
    if not module_name or not attr:
        raise ValueError(f"name {reference!r} must look like 'package.module:attr'")
    try:
        target: Any = import_user_module(module_name)
    except Exception as exc:  # the user's module may fail in any way: a syntax error, a raise
        raise ValueError(f"cannot import module {module_name!r} of surface {reference!r}: "
                         f"{type(exc).__name__}: {exc}") from exc
    for part in attr.split("."):
        if not hasattr(target, part):
            raise ValueError(f"surface {reference!r}: {module_name!r} has no attribute {attr!r}")
        target = getattr(target, part)
    if isinstance(target, type) or not isinstance(target, Surface):
        if not callable(target):
            raise ValueError(f"surface {reference!r} is neither a surface nor callable")
        try:
            target = target()
        except Exception as exc:  # the user's factory may fail in any way
            raise ValueError(f"surface {reference!r} failed to build: "
                             f"{type(exc).__name__}: {exc}") from exc
    if isinstance(target, type) or not isinstance(target, Surface):
        raise ValueError(f"surface {reference!r} did not give an object with height, gradient "
                         f"and hessian methods, got {type(target).__name__}")
    return target


def surface_leader_start(surface: Surface) -> LeaderStart | None:
    """The surface's default leader start ``(x, y, vx, vy)``, or None if it has none.

    Presets have one; a custom surface may define a ``default_leader_start`` attribute.

    Raises
    ------
    ValueError
        If ``default_leader_start`` is present but not four finite numbers.
    """
    start = getattr(surface, "default_leader_start", None)
    if start is None:
        return None
    values = np.asarray(start, dtype=float)
    if values.shape != (4,) or not np.all(np.isfinite(values)):
        raise ValueError(f"surface.default_leader_start must be four finite numbers "
                         f"(x, y, vx, vy), got {start!r}")
    return (float(values[0]), float(values[1]), float(values[2]), float(values[3]))
