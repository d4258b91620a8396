"""Surfaces and Riemannian geometry (design §3) against analytic and independent ground truth."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from numpy.typing import ArrayLike

from world.geometry import (
    SurfaceDomainError,
    heading_at_rod_end,
    ideal_formation,
    integrate_geodesic,
    metric,
    rod_end,
    rod_normal,
)
from world.surfaces import (
    PRESETS,
    Elliptic,
    GaussianHill,
    Hemisphere,
    Plane,
    make_surface,
    preset_derivatives,
    surface_leader_start,
)

REPO_ROOT = Path(__file__).resolve().parents[1]
SPACING, COMM_PERIOD = 3.57, 1.28
PAPER_PRESETS = ("elliptic", "hyperbolic", "wavy")


class PythonSurface:
    """A non-preset wrapper around a surface's numpy methods: forces the Python path."""

    def __init__(self, inner: object) -> None:
        self.inner = inner
        if hasattr(inner, "contains"):
            self.contains = inner.contains

    def height(self, p: ArrayLike) -> float:
        return self.inner.height(p)

    def gradient(self, p: ArrayLike) -> np.ndarray:
        return self.inner.gradient(p)

    def hessian(self, p: ArrayLike) -> np.ndarray:
        return self.inner.hessian(p)


def g_inner(surface: object, p: ArrayLike, a: ArrayLike, b: ArrayLike) -> float:
    return float(np.asarray(a) @ metric(surface, p) @ np.asarray(b))


def reference_geodesic(surface: object, p: ArrayLike, v: ArrayLike,
                       t: float) -> tuple[np.ndarray, np.ndarray]:
    """The geodesic ODE written out independently, solved by scipy DOP853 at 1e-13."""
    from scipy.integrate import solve_ivp  # here: every pytest worker imports this module

    def field(_: float, state: np.ndarray) -> np.ndarray:
        gradient, hessian = surface.gradient(state[:2]), surface.hessian(state[:2])
        velocity = state[2:]
        curvature = velocity @ hessian @ velocity / (1.0 + gradient @ gradient)
        return np.concatenate([velocity, -gradient * curvature])

    solution = solve_ivp(field, (0.0, t), np.concatenate([p, v]), method="DOP853",
                         rtol=1e-13, atol=1e-13)
    assert solution.success, solution.message
    return solution.y[:2, -1], solution.y[2:, -1]


def sample_poses(name: str, count: int, seed: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
    """Random positions near the preset's leader start and random headings."""
    rng = np.random.default_rng(seed)
    start = np.array(surface_leader_start(PRESETS[name]())[:2])
    spread = 3.0 if name == "hemisphere" else 8.0
    return [(start + rng.normal(0.0, spread, 2), rng.normal(size=2)) for _ in range(count)]


def lift(surface: object, p: ArrayLike) -> np.ndarray:
    """The 3-D point (x, y, F(x, y))."""
    return np.array([p[0], p[1], surface.height(p)])


# --- surfaces ---------------------------------------------------------------------------------

@pytest.mark.parametrize("name", list(PRESETS))
def test_preset_derivatives_match_finite_differences(name: str) -> None:
    surface = PRESETS[name]()
    step = 1e-5
    for p, _ in sample_poses(name, 5):
        for axis in range(2):
            e = np.eye(2)[axis] * step
            slope = (surface.height(p + e) - surface.height(p - e)) / (2 * step)
            bend = (surface.gradient(p + e) - surface.gradient(p - e)) / (2 * step)
            assert surface.gradient(p)[axis] == pytest.approx(slope, rel=1e-6, abs=1e-8)
            np.testing.assert_allclose(surface.hessian(p)[axis], bend, rtol=1e-6, atol=1e-8)


@pytest.mark.parametrize("name", list(PRESETS))
def test_kernel_matches_numpy_methods(name: str) -> None:
    surface = PRESETS[name]()
    for p, _ in sample_poses(name, 5):
        inside, fx, fy, fxx, fxy, fyy = preset_derivatives(surface.kind, surface.params, *p)
        assert inside
        np.testing.assert_allclose([fx, fy], surface.gradient(p), rtol=1e-13, atol=1e-15)
        np.testing.assert_allclose([[fxx, fxy], [fxy, fyy]], surface.hessian(p),
                                   rtol=1e-13, atol=1e-15)


def test_hemisphere_domain() -> None:
    surface = Hemisphere(radius=2.0)
    assert surface.contains((1.0, 1.0)) and not surface.contains((1.5, 1.5))
    assert not preset_derivatives(surface.kind, surface.params, 1.5, 1.5)[0]
    with pytest.raises(ValueError, match="p must lie inside"):
        surface.height((2.0, 0.0))


def test_make_surface_presets_and_params() -> None:
    for name, cls in PRESETS.items():
        surface = make_surface(name)
        assert type(surface) is cls and surface.name == name
        assert surface_leader_start(surface) == cls.default_leader_start
    plane = make_surface("plane", {"a": 1, "b": 2.5})
    assert (plane.a, plane.b) == (1.0, 2.5)
    np.testing.assert_array_equal(plane.params, [1.0, 2.5])
    assert make_surface("gaussian-hill", {"sigma": 3}).params.tolist() == [6.0, 3.0, 0.0, 0.0]
    assert surface_leader_start(Elliptic()) == pytest.approx(
        (50, -10, -math.cos(math.pi / 36), math.sin(math.pi / 36)), abs=1e-15)


@pytest.mark.parametrize("reference", ["tests.custom_surface:bowl", "tests.custom_surface:Bowl",
                                       "tests.custom_surface:make_bowl"])
def test_make_surface_imports_custom_surface(reference: str,
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.syspath_prepend(str(REPO_ROOT))
    surface = make_surface(reference)
    assert type(surface).__name__ == "Bowl"
    assert surface_leader_start(surface) == (50.0, -10.0, -1.0, 0.0)
    # The Python path on the same F as the elliptic preset gives the compiled path's result.
    p, heading = (48.0, -9.0), (-1.0, 0.2)
    for custom, preset in zip(rod_end(surface, p, heading, SPACING),
                              rod_end(Elliptic(), p, heading, SPACING), strict=True):
        np.testing.assert_allclose(custom, preset, rtol=0, atol=1e-12)


@pytest.mark.parametrize("name, params, message", [
    ("nowhere", None, "not a preset"),
    ("", None, "name must be"),
    ("plane", {"c": 1.0, "a": 1.0}, r"params \['c'\] are not parameters"),
    ("elliptic", {"scale": 2.0}, r"params \['scale'\]"),
    ("gaussian-hill", {"sigma": 0.0}, "sigma must be > 0"),
    ("hemisphere", {"radius": math.nan}, "radius must be finite"),
    ("plane", {"a": "steep"}, "a must be a real number"),
    ("no_such_package.module:thing", None, "cannot import module 'no_such_package.module'"),
    ("tests.custom_surface:missing", None, "has no attribute 'missing'"),
    ("tests.custom_surface:NOT_A_SURFACE", None, "neither a surface nor callable"),
    ("tests.custom_surface:bowl", {"a": 1.0}, "params apply only to presets"),
    (":bowl", None, "must look like"),
])
def test_make_surface_rejects_bad_input(name: str, params: dict | None, message: str,
                                        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.syspath_prepend(str(REPO_ROOT))
    with pytest.raises(ValueError, match=message):
        make_surface(name, params)


def test_surface_leader_start_of_custom_surfaces() -> None:
    assert surface_leader_start(PythonSurface(Elliptic())) is None
    broken = PythonSurface(Elliptic())
    broken.default_leader_start = (1.0, 2.0)
    with pytest.raises(ValueError, match="default_leader_start"):
        surface_leader_start(broken)


# --- metric, rods, headings ---------------------------------------------------------------------

def test_metric_formula() -> None:
    np.testing.assert_allclose(metric(Plane(a=2.0, b=-1.0), (3.0, 4.0)),
                               [[5.0, -2.0], [-2.0, 2.0]], rtol=0, atol=1e-15)


@pytest.mark.parametrize("a, b", [(0.3, -0.2), (1.5, 2.0), (0.0, 0.0)])
def test_plane_geodesics_are_straight_lines(a: float, b: float) -> None:
    surface = Plane(a=a, b=b)
    p, v = np.array([1.0, -2.0]), np.array([0.7, 1.9])
    for t in (0.0, 0.5, 3.0, 40.0):
        end, velocity = integrate_geodesic(surface, p, v, t)
        np.testing.assert_allclose(end, p + t * v, rtol=0, atol=1e-10)
        np.testing.assert_allclose(velocity, v, rtol=0, atol=1e-12)


@pytest.mark.parametrize("side", [1, -1])
@pytest.mark.parametrize("a, b", [(0.3, -0.2), (1.5, 2.0)])
def test_plane_rod_end_exact(a: float, b: float, side: int) -> None:
    surface = Plane(a=a, b=b)
    p, heading, d = np.array([4.0, 1.0]), np.array([0.6, -0.3]), 7.5
    normal_3d = np.array([-a, -b, 1.0]) / math.hypot(a, b, 1.0)
    heading_3d = np.array([heading[0], heading[1], a * heading[0] + b * heading[1]])
    across = np.cross(normal_3d, heading_3d)
    expected = p + side * d * across[:2] / np.linalg.norm(across)
    end, u = rod_end(surface, p, heading, d, side)
    np.testing.assert_allclose(end, expected, rtol=0, atol=1e-10)
    offset = end - p
    assert math.sqrt(g_inner(surface, p, offset, offset)) == pytest.approx(d, rel=0, abs=1e-10)
    np.testing.assert_allclose(u, side * across[:2] / np.linalg.norm(across), atol=1e-12)


@pytest.mark.parametrize("side", [1, -1])
@pytest.mark.parametrize("name", list(PRESETS))
def test_rod_normal_is_g_unit_and_g_orthogonal(name: str, side: int) -> None:
    surface = PRESETS[name]()
    for p, heading in sample_poses(name, 4):
        n = rod_normal(surface, p, heading, side)
        assert g_inner(surface, p, n, heading) == pytest.approx(0.0, abs=1e-12)
        assert g_inner(surface, p, n, n) == pytest.approx(1.0, abs=1e-12)
        # Left means counter-clockwise from the heading in xy.
        assert side * (heading[0] * n[1] - heading[1] * n[0]) > 0


@pytest.mark.parametrize("name", PAPER_PRESETS)
def test_rod_is_unit_speed_so_its_length_is_the_spacing(name: str) -> None:
    """A unit-speed curve over [0, d] has length d; check the speed at points along the rod."""
    surface = PRESETS[name]()
    p, heading = sample_poses(name, 1)[0]
    n = rod_normal(surface, p, heading)
    for s in np.linspace(0.0, SPACING, 7):
        point, velocity = integrate_geodesic(surface, p, n, s)
        assert g_inner(surface, point, velocity, velocity) == pytest.approx(1.0, abs=1e-10)
    end, u = rod_end(surface, p, heading, SPACING)
    assert g_inner(surface, end, u, u) == pytest.approx(1.0, abs=1e-14)


@pytest.mark.parametrize("side", [1, -1])
@pytest.mark.parametrize("name", list(PRESETS))
def test_heading_at_rod_end_continues_the_rod(name: str, side: int) -> None:
    surface = PRESETS[name]()
    for p, heading in sample_poses(name, 3):
        end, u = rod_end(surface, p, heading, SPACING, side)
        h = heading_at_rod_end(surface, end, u, side)
        assert g_inner(surface, end, h, u) == pytest.approx(0.0, abs=1e-12)
        assert g_inner(surface, end, h, h) == pytest.approx(1.0, abs=1e-12)
        np.testing.assert_allclose(rod_normal(surface, end, h, side), u, rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", list(PRESETS))
def test_rod_end_matches_scipy_dop853(name: str) -> None:
    surface = PRESETS[name]()
    for side in (1, -1):
        for p, heading in sample_poses(name, 4, seed=side + 7):
            end, u = rod_end(surface, p, heading, SPACING, side)
            expected_end, expected_velocity = reference_geodesic(
                surface, p, rod_normal(surface, p, heading, side), SPACING)
            np.testing.assert_allclose(end, expected_end, rtol=0, atol=1e-8)
            np.testing.assert_allclose(u, expected_velocity, rtol=0, atol=1e-8)


@pytest.mark.parametrize("name", list(PRESETS))
def test_python_path_matches_compiled_path(name: str) -> None:
    surface = PRESETS[name]()
    wrapped = PythonSurface(surface)
    p, heading = sample_poses(name, 1, seed=3)[0]
    for python, compiled in zip(rod_end(wrapped, p, heading, SPACING),
                                rod_end(surface, p, heading, SPACING), strict=True):
        np.testing.assert_allclose(python, compiled, rtol=0, atol=1e-11)
    for python, compiled in zip(integrate_geodesic(wrapped, p, heading, 2.0),
                                integrate_geodesic(surface, p, heading, 2.0), strict=True):
        np.testing.assert_allclose(python, compiled, rtol=0, atol=1e-11)


def test_zero_length_rod_and_zero_duration() -> None:
    surface = GaussianHill()
    p, heading = np.array([-3.0, 2.0]), np.array([1.0, 1.0])
    end, u = rod_end(surface, p, heading, 0.0)
    np.testing.assert_array_equal(end, p)
    np.testing.assert_allclose(u, rod_normal(surface, p, heading), atol=1e-15)
    end, velocity = integrate_geodesic(surface, p, heading, 0.0)
    np.testing.assert_array_equal(end, p)
    np.testing.assert_array_equal(velocity, heading)


# --- hemisphere: great circles ----------------------------------------------------------------

def test_hemisphere_meridian_leader_and_followers() -> None:
    radius = 20.0
    surface = Hemisphere(radius=radius)
    n_ticks = 12
    formation = ideal_formation(surface, (0.0, 0.0, 1.0, 0.0), 3, SPACING, COMM_PERIOD, n_ticks)
    assert formation.shape == (4, n_ticks, 2)
    leader = formation[0]
    times = COMM_PERIOD * np.arange(n_ticks)
    assert np.max(np.abs(leader[:, 1])) < 1e-9
    # Unit speed at the pole, so the leader's arc length is t.
    np.testing.assert_allclose(leader[:, 0], radius * np.sin(times / radius), rtol=0, atol=1e-9)
    for k in (1, 2, 3):
        np.testing.assert_allclose(formation[k, :, 1], radius * math.sin(k * SPACING / radius),
                                   rtol=0, atol=1e-8)
    right = ideal_formation(surface, (0.0, 0.0, 1.0, 0.0), 3, SPACING, COMM_PERIOD, 4, side=-1)
    np.testing.assert_allclose(right[1:, :, 1], -formation[1:, :4, 1], rtol=0, atol=1e-12)


def test_hemisphere_tilted_great_circle() -> None:
    radius = 20.0
    surface = Hemisphere(radius=radius)
    start = np.array([3.0, -2.0, 0.6, 0.8])
    formation = ideal_formation(surface, start, 3, SPACING, COMM_PERIOD, 8)
    gradient = surface.gradient(start[:2])
    velocity_3d = np.array([start[2], start[3], gradient @ start[2:]])
    plane_normal = np.cross(lift(surface, start[:2]), velocity_3d)
    plane_normal /= np.linalg.norm(plane_normal)
    leader_offsets = [plane_normal @ lift(surface, p) for p in formation[0]]
    assert np.max(np.abs(leader_offsets)) < 1e-9
    for k in (1, 2, 3):
        offsets = [abs(plane_normal @ lift(surface, p)) for p in formation[k]]
        np.testing.assert_allclose(offsets, radius * math.sin(k * SPACING / radius),
                                   rtol=0, atol=1e-8)


def test_hemisphere_geodesics_follow_great_circles_up_to_the_rim() -> None:
    """From random states: the great-circle point short of the rim, an error past it."""
    radius = 20.0
    surface = Hemisphere(radius=radius)
    rng = np.random.default_rng(5)
    for _ in range(25):
        p, v = rng.uniform(-10.0, 10.0, 2), rng.normal(size=2) * rng.uniform(0.2, 3.0)
        position = lift(surface, p)
        velocity = np.array([v[0], v[1], surface.gradient(p) @ v])
        speed = np.linalg.norm(velocity)
        tangent = velocity / speed
        # position·cos(s/R) + R·tangent·sin(s/R) has z = 0 at the rim.
        rim_arc = radius * (math.atan2(position[2], -radius * tangent[2]) % math.pi)
        for fraction in (0.5, 0.99):
            angle = fraction * rim_arc / radius
            expected = position * math.cos(angle) + radius * tangent * math.sin(angle)
            end, _ = integrate_geodesic(surface, p, v, fraction * rim_arc / speed)
            np.testing.assert_allclose(end, expected[:2], rtol=0, atol=1e-8)
        for fraction in (1.001, 1.5):
            with pytest.raises(SurfaceDomainError):
                integrate_geodesic(surface, p, v, fraction * rim_arc / speed)


def test_rod_leaving_the_hemisphere_raises() -> None:
    surface = Hemisphere(radius=20.0)
    with pytest.raises(SurfaceDomainError, match="rod leaves the surface's domain"):
        rod_end(surface, (0.0, 0.0), (0.0, -1.0), 40.0)
    with pytest.raises(SurfaceDomainError, match="rod leaves the surface's domain"):
        rod_end(surface, (5.0, 3.0), (1.0, 2.0), 60.0)
    with pytest.raises(SurfaceDomainError, match="outside the surface's domain"):
        rod_end(surface, (25.0, 0.0), (1.0, 0.0), 1.0)
    with pytest.raises(SurfaceDomainError, match="geodesic leaves"):
        integrate_geodesic(surface, (0.0, 0.0), (3.0, 0.0), 20.0)
    with pytest.raises(SurfaceDomainError, match="rod leaves the surface's domain"):
        rod_end(PythonSurface(surface), (0.0, 0.0), (0.0, -1.0), 40.0)


# --- formation --------------------------------------------------------------------------------

@pytest.mark.parametrize("side", [1, -1])
@pytest.mark.parametrize("name", PAPER_PRESETS)
def test_chained_rods_agree_with_one_long_geodesic(name: str, side: int) -> None:
    """Gauss lemma: follower k sits at distance k·d along the leader's rod geodesic."""
    surface = PRESETS[name]()
    start = surface_leader_start(surface)
    n_ticks, n_followers = 10, 4
    formation = ideal_formation(surface, start, n_followers, SPACING, COMM_PERIOD, n_ticks, side)
    position, velocity = np.array(start[:2]), np.array(start[2:])
    for j in range(n_ticks):
        if j:
            position, velocity = integrate_geodesic(surface, position, velocity, COMM_PERIOD)
        np.testing.assert_array_equal(formation[0, j], position)
        for k in range(1, n_followers + 1):
            end, _ = rod_end(surface, position, velocity, k * SPACING, side)
            np.testing.assert_allclose(formation[k, j], end, rtol=0, atol=1e-8)


def test_ideal_formation_defaults_and_determinism() -> None:
    surface = make_surface("wavy")
    first = ideal_formation(surface, None, 2, SPACING, COMM_PERIOD, 6)
    again = ideal_formation(surface, surface_leader_start(surface), 2, SPACING, COMM_PERIOD, 6)
    np.testing.assert_array_equal(first, again)
    np.testing.assert_array_equal(first[0, 0], surface_leader_start(surface)[:2])
    assert ideal_formation(surface, None, 0, SPACING, COMM_PERIOD, 1).shape == (1, 1, 2)


@pytest.mark.parametrize("call, message", [
    (lambda s: rod_normal(s, (0, 0), (1, 0), side=0), "side must be"),
    (lambda s: rod_normal(s, (0, 0), (1, 0), side=True), "side must be"),
    (lambda s: rod_end(s, (0, 0), (1, 0), 1.0, side=2), "side must be"),
    (lambda s: rod_end(s, (0, 0), (0, 0), 1.0), "heading must be a nonzero"),
    (lambda s: rod_end(s, (0, 0), (1, 0), -1.0), "length must be >= 0"),
    (lambda s: rod_end(s, (0, 0, 0), (1, 0), 1.0), "p must be 2 finite numbers"),
    (lambda s: rod_end(s, (0, math.nan), (1, 0), 1.0), "p must be 2 finite numbers"),
    (lambda s: integrate_geodesic(s, (0, 0), (1, 0), -0.5), "t must be >= 0"),
    (lambda s: integrate_geodesic(s, (0, 0), (1, 0), math.inf), "t must be a finite"),
    (lambda s: heading_at_rod_end(s, (0, 0), (0, 0)), "u must be a nonzero"),
    (lambda s: ideal_formation(s, (0, 0, 1), 1, 1.0, 1.0, 3), "leader_start must be 4"),
    (lambda s: ideal_formation(s, (0, 0, 0, 0), 1, 1.0, 1.0, 3), "nonzero velocity"),
    (lambda s: ideal_formation(s, (0, 0, 1, 0), -1, 1.0, 1.0, 3), "n_followers must be"),
    (lambda s: ideal_formation(s, (0, 0, 1, 0), 1, 0.0, 1.0, 3), "spacing must be > 0"),
    (lambda s: ideal_formation(s, (0, 0, 1, 0), 1, 1.0, -1.0, 3), "comm_period must be > 0"),
    (lambda s: ideal_formation(s, (0, 0, 1, 0), 1, 1.0, 1.0, 0), "n_ticks must be"),
    (lambda s: ideal_formation(s, (0, 0, 1, 0), 1, 1.0, 1.0, 2.5), "n_ticks must be"),
    (lambda s: ideal_formation(PythonSurface(s), None, 1, 1.0, 1.0, 2), "leader_start is"),
    (lambda s: rod_end(object(), (0, 0), (1, 0), 1.0), "surface must have"),
])
def test_bad_arguments_raise_value_error(call: object, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        call(Plane())
