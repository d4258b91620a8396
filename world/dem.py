"""Real terrain: a digital elevation model (DEM) as a surface, ``dem:PATH`` (design §3).

Loading
-------
:func:`read_dem` reads band 1 of any raster GDAL opens through ``rasterio`` — a GeoTIFF or an
ESRI ASCII grid (``.asc``, with an optional ``.prj`` beside it) — and returns the grid in
the design's frame: metres, x east, y north, origin at the centre of the south-west cell, node
``(i, j)`` the centre of cell (column i, row j counted from the south).

- A projected raster whose linear unit is the metre is used as is.
- A geographic raster (degrees; EPSG:4326) is put in metres by the local equirectangular rule
  on a sphere of radius 6,371,008.8 m about the raster's centre latitude φ₀: ``m = R·π/180``
  metres per degree north, ``m·cos φ₀`` per degree east.
- A raster without any CRS (an ASCII grid without ``.prj``) is taken to be in metres.
- Anything else (feet, a rotated grid, no-data cells, fewer than 4 × 4 nodes) is refused with
  a ``ValueError`` saying why.
- A raster whose header claims more than :data:`MAX_CELLS` cells (width × height) is refused
  with :class:`RasterTooLarge` before any of its data is read: loading takes about
  :data:`BYTES_PER_CELL` bytes of memory per cell. A run may raise the limit with the surface
  parameter ``max_cells`` (TOML ``[surface_params] max_cells = ...``); ``python -m swarm
  dem-crop`` cuts a large raster down.

Surface
-------
:class:`DemSurface` is ``F = RectBivariateSpline(y, x, z, kx=3, ky=3, s=smoothing)`` on the
rectangle of node centres. Its numpy methods evaluate scipy's spline with its own derivatives;
its ``params`` pack the spline's knots and coefficients for :func:`spline_surface`, a numba
kernel of this module that evaluates the same B-spline (value, gradient, Hessian) inside the
compiled geodesic integrator of :mod:`world.geometry`.

The spline is a cubic polynomial on each knot cell but only C² across knot lines, so the
integrator must not let one Bulirsch–Stoer step straddle a knot line (its error estimate
assumes a smooth field). :func:`knot_step_limit` bounds a step so that the path, predicted to
second order, ends just past the next knot line, and :func:`knot_step_shrink` rejects a step
that ended farther than that and proposes a shorter one. Each knot line is thus crossed by at
most ``1e-8`` of a cell width inside one step.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any, ClassVar

import numba
import numpy as np
from numba.extending import register_jitable
from numpy.typing import ArrayLike

from protocol.cli import Refused
from world.surfaces import DEM_PREFIX

DEM_KIND = 100
"""The ``kind`` code of a DEM context ``(DEM_KIND, params)`` (presets use 0 … 6)."""
EARTH_RADIUS = 6_371_008.8
"""Mean Earth radius (m) of the equirectangular rule."""
METRES_PER_DEGREE = EARTH_RADIUS * math.pi / 180.0
MIN_NODES = 4
"""A bicubic spline needs at least 4 nodes along each axis."""
KNOT_MARGIN = 1e-8
"""How far past a knot line (in cell widths) one integration step may end."""
MAX_CELLS = 4096 * 4096
"""Most cells (width × height) of a DEM a run loads unless its ``max_cells`` says otherwise:
about 0.4 GiB of memory at :data:`BYTES_PER_CELL`."""
BYTES_PER_CELL = 24
"""Peak memory per cell while a DEM is loaded: the heights as float64, their copies, and
scipy's spline coefficients and working memory (measured 23 bytes on a 3000 × 3000 float32
GeoTIFF, about 19 for each cell more: bench/bench_dem_limit.py)."""
_HEADER = 6  # params: n_ty, n_tx, y0, y1, x0, x1, then ty, tx, coefficients


class RasterTooLarge(Refused):
    """A raster whose header claims more cells than the limit (its data was not read)."""


def read_dem(path: str | Path,
             max_cells: int = MAX_CELLS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read a DEM raster into the design §3 frame: :func:`read_grid`, no-data cells refused.

    Raises
    ------
    ValueError
        As :func:`read_grid`, and for no-data cells (their count and the first one's column
        and row, counted from the south).
    """
    x, y, z = read_grid(path, max_cells)
    missing = ~np.isfinite(z)
    if missing.any():
        j, i = np.argwhere(missing)[0]
        raise ValueError(f"path {str(path)!r}: {int(missing.sum())} no-data cell(s), e.g. column "
                         f"{i}, row {j} from the south; fill them, or keep the largest "
                         f"rectangle without any: python -m swarm dem-crop {path} OUT.tif")
    return x, y, z


def read_grid(path: str | Path, max_cells: int = MAX_CELLS,
              limit: str = "surface_params.max_cells") -> tuple[np.ndarray, np.ndarray,
                                                                  np.ndarray]:
    """Read a DEM raster into the design §3 frame, no-data cells as NaN.

    Parameters
    ----------
    path : str or Path
        A GeoTIFF, an ESRI ASCII grid, or any single-band raster rasterio opens.
    max_cells : int
        The most cells (width × height) read; the header is checked before any data.
    limit : str
        What raises ``max_cells`` (named in the refusal).

    Returns
    -------
    x : ndarray, shape (nx,)
        Node x coordinates (m, east), ``x[0] = 0``.
    y : ndarray, shape (ny,)
        Node y coordinates (m, north), ``y[0] = 0``.
    z : ndarray, shape (ny, nx)
        Heights (m); row ``j`` is the ``j``-th row from the south; NaN where the raster has
        no data.

    Raises
    ------
    RasterTooLarge
        The header claims more than ``max_cells`` cells.
    ValueError
        Missing or unreadable file, rotated grid, unknown CRS units, or fewer than 4 × 4
        nodes.
    """
    from protocol.distribution import needs  # rasterio comes with the [dem] extra

    with needs("dem"):
        import rasterio
        from rasterio.errors import CRSError, RasterioIOError

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"path {str(path)!r}: no such DEM file")
    try:
        with rasterio.open(path) as src:  # reads the header only
            check_size(path, src.width, src.height, max_cells, limit)
            band = src.read(1, masked=True)
            transform, crs = src.transform, src.crs
    except RasterioIOError as exc:
        raise ValueError(f"path {str(path)!r} is not a raster rasterio can read: {exc}") from None
    if transform.b != 0.0 or transform.d != 0.0:
        raise ValueError(f"path {str(path)!r}: the grid is rotated or sheared "
                         f"(transform {tuple(transform)[:6]}); only north-up grids are supported")
    rows, cols = band.shape
    if rows < MIN_NODES or cols < MIN_NODES:
        raise ValueError(f"path {str(path)!r}: a {cols} × {rows} grid is too small for a bicubic "
                         f"spline (at least {MIN_NODES} × {MIN_NODES} nodes)")
    z = np.ma.filled(band.astype(np.float64), np.nan)
    if transform.e < 0:  # row 0 is the northern edge: count rows from the south
        z = z[::-1]
    step_x, step_y = abs(transform.a), abs(transform.e)
    if crs is None:
        scale_x = scale_y = 1.0
    elif crs.is_geographic:
        unit, _ = crs.units_factor
        if unit not in ("degree", "degrees"):
            raise ValueError(f"path {str(path)!r}: geographic CRS with unit {unit!r}; "
                             "only degrees are supported")
        south = transform.f + transform.e * rows if transform.e < 0 else transform.f
        centre_latitude = south + step_y * rows / 2.0
        scale_y = METRES_PER_DEGREE
        scale_x = METRES_PER_DEGREE * math.cos(math.radians(centre_latitude))
    else:
        try:
            unit, factor = crs.units_factor
        except CRSError:
            unit, factor = "unknown", math.nan
        if factor != 1.0:
            raise ValueError(f"path {str(path)!r}: CRS {crs.to_string()!r} has linear unit "
                             f"{unit!r}; only metres (or degrees for EPSG:4326) are supported")
        scale_x = scale_y = 1.0
    x = np.arange(cols) * (step_x * scale_x)
    y = np.arange(rows) * (step_y * scale_y)
    return x, y, np.ascontiguousarray(z)


def check_size(path: str | Path, width: int, height: int, max_cells: int, limit: str) -> None:
    """Refuse (:class:`RasterTooLarge`) a ``width`` × ``height`` raster over ``max_cells``,
    naming its size, the memory it would take, the ``limit`` that raises it, and dem-crop."""
    cells = width * height
    if cells <= max_cells:
        return
    gib = 2.0 ** 30
    raise RasterTooLarge(
        f"path {str(path)!r}: a {width} × {height} raster ({cells:,} cells, "
        f"{cells * 8 / gib:,.1f} GiB as float64, about {cells * BYTES_PER_CELL / gib:,.1f} GiB "
        f"to load) is over the limit of {max_cells:,} cells ({limit} raises it); cut out the "
        f"part you need first: python -m swarm dem-crop {path} OUT.tif --bounds "
        "XMIN,YMIN,XMAX,YMAX")


class DemSurface:
    """Bicubic interpolating (or smoothing) spline through a DEM's nodes (design §3).

    Parameters
    ----------
    x : array_like, shape (nx,)
        Strictly increasing node x coordinates (m).
    y : array_like, shape (ny,)
        Strictly increasing node y coordinates (m).
    z : array_like, shape (ny, nx)
        Heights (m); ``z[j, i]`` at ``(x[i], y[j])``.
    smoothing : float
        scipy's ``s`` (0: interpolation).
    source : str
        Where the grid came from (for messages).

    Attributes
    ----------
    spline : scipy.interpolate.RectBivariateSpline
        ``RectBivariateSpline(y, x, z, kx=3, ky=3, s=smoothing)``.
    kind : int
        :data:`DEM_KIND`.
    params : ndarray
        Read-only packed knots and coefficients for :func:`spline_surface`.
    bounds : tuple of float
        ``(x0, x1, y0, y1)``: the domain, the rectangle of node centres.
    """

    kind: ClassVar[int] = DEM_KIND
    default_leader_start: ClassVar[None] = None

    def __init__(self, x: ArrayLike, y: ArrayLike, z: ArrayLike, smoothing: float = 0.0,
                 source: str = "grid") -> None:
        from scipy.interpolate import RectBivariateSpline

        self.x, self.y = _axis(x, "x"), _axis(y, "y")
        self.z = np.asarray(z, dtype=float)
        if self.z.shape != (self.y.size, self.x.size):
            raise ValueError(f"z must have shape (len(y), len(x)) = {(self.y.size, self.x.size)}, "
                             f"got {self.z.shape}")
        if not np.isfinite(self.z).all():
            raise ValueError("z must be finite (no-data cells are not allowed)")
        if (isinstance(smoothing, bool) or not isinstance(smoothing, (int, float))
                or not math.isfinite(smoothing) or smoothing < 0):
            raise ValueError(f"smoothing must be a finite number >= 0, got {smoothing!r}")
        self.smoothing = float(smoothing)
        self.source = source
        self.spline = RectBivariateSpline(self.y, self.x, self.z, kx=3, ky=3, s=self.smoothing)
        self.bounds = (float(self.x[0]), float(self.x[-1]), float(self.y[0]), float(self.y[-1]))
        ty, tx = self.spline.tck[0], self.spline.tck[1]
        if np.any(np.diff(tx) < 0) or np.any(np.diff(ty) < 0):
            # Seen with scipy 1.17 for some s > 0: FITPACK's smoothing fit hands back an
            # unsorted knot vector, which is no B-spline (scipy still evaluates it, wildly).
            raise ValueError(f"smoothing = {self.smoothing:g} on this grid makes scipy's "
                             "RectBivariateSpline return unsorted knots (a failed FITPACK fit); "
                             "choose another smoothing, or 0 to interpolate")
        coefficients = np.asarray(self.spline.tck[2], dtype=float)
        params = np.concatenate([[ty.size, tx.size, self.bounds[2], self.bounds[3],
                                  self.bounds[0], self.bounds[1]], ty, tx, coefficients])
        params.flags.writeable = False
        self.params = params

    def __repr__(self) -> str:
        return (f"DemSurface({self.source!r}, {self.x.size} × {self.y.size} nodes, "
                f"smoothing={self.smoothing:g})")

    def contains(self, p: ArrayLike) -> bool:
        """Whether ``p`` lies in the closed rectangle of node centres."""
        x, y = _point(p)
        x0, x1, y0, y1 = self.bounds
        return x0 <= x <= x1 and y0 <= y <= y1

    def _inside(self, p: ArrayLike) -> tuple[float, float]:
        x, y = _point(p)
        if not self.contains((x, y)):
            raise ValueError(f"p = ({x:.6g}, {y:.6g}) lies outside the DEM grid "
                             f"{_describe(self.bounds)}")
        return x, y

    def _ev(self, p: ArrayLike, order_x: int, order_y: int) -> float:
        x, y = self._inside(p)
        return float(self.spline.ev(y, x, dx=order_y, dy=order_x))

    def height(self, p: ArrayLike) -> float:
        """``F(p)`` (m)."""
        return self._ev(p, 0, 0)

    def gradient(self, p: ArrayLike) -> np.ndarray:
        """``(Fx, Fy)`` at ``p``, shape (2,)."""
        return np.array([self._ev(p, 1, 0), self._ev(p, 0, 1)])

    def hessian(self, p: ArrayLike) -> np.ndarray:
        """``[[Fxx, Fxy], [Fxy, Fyy]]`` at ``p``, shape (2, 2)."""
        fxy = self._ev(p, 1, 1)
        return np.array([[self._ev(p, 2, 0), fxy], [fxy, self._ev(p, 0, 2)]])


def load_dem(path: str | Path, smoothing: float = 0.0,
             max_cells: int = MAX_CELLS) -> DemSurface:
    """The surface of the DEM at ``path`` (see :func:`read_dem` and :class:`DemSurface`)."""
    x, y, z = read_dem(path, max_cells)
    return DemSurface(x, y, z, smoothing=smoothing, source=str(path))


def make_dem_surface(name: str, params: dict[str, Any]) -> DemSurface:
    """``make_surface`` for ``"dem:PATH"``; its parameters are ``smoothing`` and ``max_cells``
    (the raster limit, default :data:`MAX_CELLS`)."""
    path = name[len(DEM_PREFIX):]
    if not path:
        raise ValueError(f"name {name!r} must be 'dem:PATH' with a file path")
    unknown = sorted(set(params) - {"smoothing", "max_cells"})
    if unknown:
        raise ValueError(f"params {unknown} are not parameters of a DEM surface "
                         "(it takes smoothing and max_cells)")
    max_cells = params.get("max_cells", MAX_CELLS)
    if isinstance(max_cells, bool) or not isinstance(max_cells, (int, float)) \
            or not float(max_cells).is_integer() or max_cells < 1:
        raise ValueError(f"surface_params.max_cells must be a whole number of cells >= 1, got "
                         f"{max_cells!r}")
    return load_dem(path, params.get("smoothing", 0.0), int(max_cells))


def describe_domain(params: np.ndarray) -> str:
    """The packed DEM's domain, for error messages."""
    return _describe((params[4], params[5], params[2], params[3]))


def _describe(bounds: tuple[float, float, float, float]) -> str:
    x0, x1, y0, y1 = bounds
    return f"x ∈ [{x0:.6g}, {x1:.6g}], y ∈ [{y0:.6g}, {y1:.6g}] (m)"


def _axis(values: ArrayLike, name: str) -> np.ndarray:
    axis = np.asarray(values, dtype=float)
    if axis.ndim != 1 or axis.size < MIN_NODES:
        raise ValueError(f"{name} must be 1-D with at least {MIN_NODES} nodes for a bicubic "
                         f"spline, got shape {axis.shape}")
    if not np.isfinite(axis).all() or not np.all(np.diff(axis) > 0):
        raise ValueError(f"{name} must be finite and strictly increasing")
    return axis


def _point(p: ArrayLike) -> tuple[float, float]:
    point = np.asarray(p, dtype=float)
    if point.shape != (2,) or not np.isfinite(point).all():
        raise ValueError(f"p must be a finite point (x, y) of shape (2,), got {p!r}")
    return float(point[0]), float(point[1])


# --- compiled evaluation ------------------------------------------------------------------------

@register_jitable
def _span(knots: np.ndarray, start: int, n_knots: int, u: float) -> int:
    """Index ``j`` (into the whole params array) of the knot interval holding ``u``.

    ``knots[start : start + n_knots]`` is a cubic knot vector; ``j`` satisfies
    ``t[j] <= u < t[j+1]`` clamped to the first and last nonempty intervals.
    """
    low, high = start + 3, start + n_knots - 4
    if u >= knots[high]:
        return high - 1
    if u <= knots[low]:
        return low
    while high - low > 1:
        middle = (low + high) // 2
        if u >= knots[middle]:
            low = middle
        else:
            high = middle
    return low


@register_jitable
def _cubic_basis(t: np.ndarray, j: int, u: float) -> tuple[float, ...]:
    """Cubic B-spline basis on knot interval ``j`` and its two derivatives at ``u``.

    Returns 12 floats: ``N_{j-3+r,3}(u)``, then their first, then their second derivatives
    (r = 0 … 3). The Cox–de Boor recursion written out for degree 3; every denominator spans
    the nonempty interval ``[t_j, t_{j+1}]``, so none is zero.
    """
    tm2, tm1, t0, t1, t2, t3 = t[j - 2], t[j - 1], t[j], t[j + 1], t[j + 2], t[j + 3]
    inv_w = 1.0 / (t1 - t0)
    a1, b1 = (t1 - u) * inv_w, (u - t0) * inv_w  # N_{j-1,1}, N_{j,1}
    g1, g2 = a1 / (t1 - tm1), b1 / (t2 - t0)
    n20 = (t1 - u) * g1  # N_{j-2,2}, N_{j-1,2}, N_{j,2}; their derivatives are 2·(…)
    n21 = (u - tm1) * g1 + (t2 - u) * g2
    n22 = (u - t0) * g2
    h0, h1, h2 = 1.0 / (t1 - tm2), 1.0 / (t2 - tm1), 1.0 / (t3 - t0)
    m0, m1, m2 = n20 * h0, n21 * h1, n22 * h2
    d0, d1, d2 = -2.0 * g1 * h0, 2.0 * (g1 - g2) * h1, 2.0 * g2 * h2
    return ((t1 - u) * m0, (u - tm2) * m0 + (t2 - u) * m1, (u - tm1) * m1 + (t3 - u) * m2,
            (u - t0) * m2,
            -3.0 * m0, 3.0 * (m0 - m1), 3.0 * (m1 - m2), 3.0 * m2,
            -3.0 * d0, 3.0 * (d0 - d1), 3.0 * (d1 - d2), 3.0 * d2)


@register_jitable
def _row(params: np.ndarray, base: int, basis: tuple[float, ...]) -> tuple[float, float, float]:
    """Four coefficients from ``params[base]`` against a :func:`_cubic_basis` (three orders)."""
    c0, c1, c2, c3 = params[base], params[base + 1], params[base + 2], params[base + 3]
    return (c0 * basis[0] + c1 * basis[1] + c2 * basis[2] + c3 * basis[3],
            c0 * basis[4] + c1 * basis[5] + c2 * basis[6] + c3 * basis[7],
            c0 * basis[8] + c1 * basis[9] + c2 * basis[10] + c3 * basis[11])


@numba.njit(cache=True)
def spline_surface(params: np.ndarray, x: float,
                   y: float) -> tuple[bool, float, float, float, float, float, float]:
    """Value and derivatives of the packed DEM spline at ``(x, y)``.

    Parameters
    ----------
    params : ndarray
        :attr:`DemSurface.params`.
    x, y : float
        The point (m).

    Returns
    -------
    inside : bool
        Whether ``(x, y)`` lies in the rectangle of node centres (the rest is NaN otherwise).
    f, fx, fy, fxx, fxy, fyy : float
        ``F`` and its first and second partial derivatives.
    """
    nan = math.nan
    n_ty, n_tx = int(params[0]), int(params[1])
    if not (params[4] <= x <= params[5] and params[2] <= y <= params[3]):
        return False, nan, nan, nan, nan, nan, nan
    start_y, start_x = _HEADER, _HEADER + n_ty
    start_c = start_x + n_tx
    n_cx = n_tx - 4
    ly, lx = _span(params, start_y, n_ty, y), _span(params, start_x, n_tx, x)
    (ny0, ny1, ny2, ny3, dy0, dy1, dy2, dy3,
     sy0, sy1, sy2, sy3) = _cubic_basis(params, ly, y)
    bx = _cubic_basis(params, lx, x)
    base = start_c + (ly - start_y - 3) * n_cx + (lx - start_x - 3)
    # Row a of the 4 × 4 coefficient block against the x basis (value, first, second derivative).
    r00, r01, r02 = _row(params, base, bx)
    r10, r11, r12 = _row(params, base + n_cx, bx)
    r20, r21, r22 = _row(params, base + 2 * n_cx, bx)
    r30, r31, r32 = _row(params, base + 3 * n_cx, bx)
    f = ny0 * r00 + ny1 * r10 + ny2 * r20 + ny3 * r30
    fx = ny0 * r01 + ny1 * r11 + ny2 * r21 + ny3 * r31
    fxx = ny0 * r02 + ny1 * r12 + ny2 * r22 + ny3 * r32
    fy = dy0 * r00 + dy1 * r10 + dy2 * r20 + dy3 * r30
    fxy = dy0 * r01 + dy1 * r11 + dy2 * r21 + dy3 * r31
    fyy = sy0 * r00 + sy1 * r10 + sy2 * r20 + sy3 * r30
    return True, f, fx, fy, fxx, fxy, fyy


@numba.njit(cache=True)
def spline_derivatives(params: np.ndarray, x: float,
                       y: float) -> tuple[bool, float, float, float, float, float]:
    """``(inside, Fx, Fy, Fxx, Fxy, Fyy)`` of the packed DEM spline, like
    :func:`world.surfaces.preset_derivatives`."""
    inside, _, fx, fy, fxx, fxy, fyy = spline_surface(params, x, y)
    return inside, fx, fy, fxx, fxy, fyy


@register_jitable
def _cell(params: np.ndarray, start: int, n_knots: int, u: float,
          velocity: float) -> tuple[float, float]:
    """Knot cell ``(low, high)`` the path enters from ``u`` moving with ``velocity``.

    A point within :data:`KNOT_MARGIN` of a knot line counts as on it: the cell is then the
    one on the side the path is moving to.
    """
    j = _span(params, start, n_knots, u)
    first, last = start + 3, start + n_knots - 5
    low, high = params[j], params[j + 1]
    margin = KNOT_MARGIN * (high - low)
    if u - low <= margin and velocity < 0.0 and j > first:
        return params[j - 1], low
    if high - u <= margin and velocity > 0.0 and j < last:
        return high, params[j + 2]
    return low, high


@register_jitable
def _first_hit(distance: float, velocity: float, acceleration: float) -> float:
    """Smallest ``τ > 0`` with ``velocity·τ + acceleration·τ²/2 = distance`` (inf if none)."""
    if acceleration == 0.0:
        if velocity == 0.0:
            return math.inf
        tau = distance / velocity
        return tau if tau > 0.0 else math.inf
    discriminant = velocity * velocity + 2.0 * acceleration * distance
    if discriminant < 0.0:
        return math.inf
    q = velocity + math.copysign(math.sqrt(discriminant), velocity)
    best = math.inf
    if q != 0.0:
        for tau in (q / acceleration, 2.0 * distance / q):
            if 0.0 < tau < best:
                best = tau
    return best


@register_jitable
def knot_step_limit(params: np.ndarray, state: np.ndarray, rate: np.ndarray) -> float:
    """Longest step from ``state`` that, to second order, ends at most just past a knot line.

    Parameters
    ----------
    params : ndarray
        :attr:`DemSurface.params`.
    state, rate : ndarray, shape (4,)
        ``(x, y, ẋ, ẏ)`` and its time derivative (so ``rate[2:]`` is the acceleration).
    """
    n_ty, n_tx = int(params[0]), int(params[1])
    limit = math.inf
    for axis in range(2):
        start = _HEADER + n_ty if axis == 0 else _HEADER
        n_knots = n_tx if axis == 0 else n_ty
        u, velocity, acceleration = state[axis], state[axis + 2], rate[axis + 2]
        low, high = _cell(params, start, n_knots, u, velocity)
        half = 0.5 * KNOT_MARGIN * (high - low)
        limit = min(limit, _first_hit(high + half - u, velocity, acceleration),
                    _first_hit(low - half - u, velocity, acceleration))
    return limit


@register_jitable
def knot_step_shrink(params: np.ndarray, state: np.ndarray, end: np.ndarray) -> float:
    """1 if a step from ``state`` ending at ``end`` stayed in its knot cell (± the margin),
    else the fraction of the step that, linearly interpolated, ends just past the knot line."""
    n_ty, n_tx = int(params[0]), int(params[1])
    shrink = 1.0
    for axis in range(2):
        start = _HEADER + n_ty if axis == 0 else _HEADER
        n_knots = n_tx if axis == 0 else n_ty
        u, moved = state[axis], end[axis] - state[axis]
        low, high = _cell(params, start, n_knots, u, state[axis + 2])
        margin = KNOT_MARGIN * (high - low)
        if end[axis] > high + margin:
            shrink = min(shrink, (high + 0.5 * margin - u) / moved)
        elif end[axis] < low - margin:
            shrink = min(shrink, (low - 0.5 * margin - u) / moved)
    return min(max(shrink, 0.01), 1.0 - 1e-9) if shrink < 1.0 else 1.0
