"""DEM surfaces (design §3 "Real terrain"): loading, the frame, the spline, compiled evaluation,
geodesics across knots, errors, figures, and end-to-end runs over Zenoh."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from protocol.config import RunConfig
from swarm.terrain import crop_dem, largest_rectangle, write_geotiff
from tests.make_dem_data import (
    HILLS,
    HILLS_CELL,
    HILLS_CRS,
    HILLS_LEADER_START,
    HILLS_SHAPE,
    hills_function,
    hills_heights,
)
from world.dem import METRES_PER_DEGREE, DemSurface, load_dem, read_dem, read_grid, spline_surface
from world.geometry import SurfaceDomainError, ideal_formation, integrate_geodesic, rod_end
from world.surfaces import make_surface

SEED = 20261123
SPACING, COMM_PERIOD = 3.57, 1.28


def sampled(function, x: np.ndarray, y: np.ndarray) -> DemSurface:
    """A DEM of ``function`` sampled at the nodes ``x`` × ``y``."""
    return DemSurface(x, y, function(*np.meshgrid(x, y)))


def write_ascii(path: Path, z_south_first: np.ndarray, cell: float,
                nodata: float | None = None) -> Path:
    """An ESRI ASCII grid (corner-registered, north row first) with ``cell``-sized cells."""
    rows, cols = z_south_first.shape
    header = [f"ncols {cols}", f"nrows {rows}", "xllcorner 1000.0", "yllcorner 2000.0",
              f"cellsize {cell!r}"]
    if nodata is not None:
        header.append(f"NODATA_value {nodata:g}")
    body = [" ".join(repr(float(v)) for v in row) for row in z_south_first[::-1]]
    path.write_text("\n".join(header + body) + "\n")
    return path


# ------------------------------------------------------------------ the surface and its frame

def test_paraboloid_dem_reproduces_the_elliptic_preset():
    """A quadratic is reproduced exactly by the bicubic spline: the same ideal formation."""
    elliptic = make_surface("elliptic")
    dem = sampled(lambda x, y: (x * x + y * y) / 30.0, np.linspace(-60.0, 70.0, 66),
                  np.linspace(-40.0, 40.0, 41))
    expected = ideal_formation(elliptic, None, 3, SPACING, COMM_PERIOD, 40)
    got = ideal_formation(dem, elliptic.default_leader_start, 3, SPACING, COMM_PERIOD, 40)
    assert np.max(np.abs(got - expected)) < 1e-8


def test_plane_dem_has_straight_geodesics():
    plane = make_surface("plane")
    dem = sampled(lambda x, y: plane.a * x + plane.b * y, np.arange(0.0, 61.0, 3.0),
                  np.arange(0.0, 41.0, 2.5))
    end, velocity = integrate_geodesic(dem, (3.0, 4.0), (1.1, 0.7), 40.0)
    np.testing.assert_allclose(end, [3.0 + 44.0, 4.0 + 28.0], atol=1e-9)
    np.testing.assert_allclose(velocity, [1.1, 0.7], atol=1e-12)
    ours, _ = rod_end(dem, (20.0, 10.0), (0.3, 1.0), 12.0)
    preset, _ = rod_end(plane, (20.0, 10.0), (0.3, 1.0), 12.0)
    np.testing.assert_allclose(ours, preset, atol=1e-9)


def test_frame_origin_and_axes_follow_the_spec(tmp_path):
    """Node (i, j) is at (i·dx, j·dy), j counted from the south, whatever the file's row order."""
    z = hills_heights()
    dem = load_dem(HILLS)
    assert dem.bounds == (0.0, (HILLS_SHAPE[1] - 1) * HILLS_CELL, 0.0,
                          (HILLS_SHAPE[0] - 1) * HILLS_CELL)
    for i, j in ((0, 0), (25, 0), (0, 20), (7, 13)):
        assert dem.height((i * HILLS_CELL, j * HILLS_CELL)) == pytest.approx(float(z[j, i]),
                                                                               abs=1e-9)


def test_same_grid_in_every_format_gives_the_same_surface(tmp_path):
    z = hills_heights().astype(np.float64)
    rows, cols = z.shape
    projected = write_geotiff(tmp_path / "projected.tif", z, west=500_000.0, south=5_200_000.0,
                              cell_x=HILLS_CELL, cell_y=HILLS_CELL, crs=HILLS_CRS)
    south = 46.5
    cell_lat = HILLS_CELL / METRES_PER_DEGREE
    centre = south + cell_lat * rows / 2.0
    cell_lon = HILLS_CELL / (METRES_PER_DEGREE * math.cos(math.radians(centre)))
    geographic = write_geotiff(tmp_path / "geographic.tif", z, west=8.0, south=south,
                               cell_x=cell_lon, cell_y=cell_lat, crs="EPSG:4326")
    ascii_grid = write_ascii(tmp_path / "grid.asc", z, HILLS_CELL)
    reference = load_dem(projected)
    rng = np.random.default_rng(SEED)
    points = np.column_stack([rng.uniform(0, 50, 50), rng.uniform(0, 40, 50)])
    for path in (geographic, ascii_grid):
        other = load_dem(path)
        np.testing.assert_allclose(other.x, reference.x, rtol=0, atol=1e-9)
        np.testing.assert_allclose(other.y, reference.y, rtol=0, atol=1e-9)
        for p in points:
            assert other.height(p) == pytest.approx(reference.height(p), abs=1e-8)
            np.testing.assert_allclose(other.gradient(p), reference.gradient(p), atol=1e-8)


def test_geographic_raster_uses_the_local_equirectangular_rule(tmp_path):
    z = np.arange(30.0).reshape(5, 6)
    path = write_geotiff(tmp_path / "geo.tif", z, west=-84.4, south=36.4, cell_x=0.001,
                         cell_y=0.002, crs="EPSG:4326")
    dem = load_dem(path)
    centre = 36.4 + 0.002 * 5 / 2
    np.testing.assert_allclose(np.diff(dem.y), 0.002 * 6_371_008.8 * math.pi / 180, rtol=1e-12)
    np.testing.assert_allclose(np.diff(dem.x), 0.001 * 6_371_008.8 * math.pi / 180
                               * math.cos(math.radians(centre)), rtol=1e-12)


def test_spline_is_scipys_rectbivariatespline(tmp_path):
    from scipy.interpolate import RectBivariateSpline

    dem = load_dem(HILLS)
    y, x = (np.arange(n) * HILLS_CELL for n in HILLS_SHAPE)
    spline = RectBivariateSpline(y, x, hills_heights().astype(np.float64), kx=3, ky=3, s=0)
    assert dem.height((13.3, 7.9)) == float(spline.ev(7.9, 13.3))
    assert dem.gradient((13.3, 7.9))[0] == float(spline.ev(7.9, 13.3, dy=1))
    smooth = make_surface(f"dem:{HILLS}", {"smoothing": 5.0})
    assert smooth.smoothing == 5.0
    assert smooth.height((13.3, 7.9)) != dem.height((13.3, 7.9))


# ------------------------------------------------------------------ compiled evaluation

@pytest.mark.parametrize("smoothing", [0.0, 2.0])
def test_compiled_spline_matches_scipy(smoothing):
    rng = np.random.default_rng(SEED)
    x = np.cumsum(rng.uniform(0.5, 3.0, 17))
    y = np.cumsum(rng.uniform(0.5, 3.0, 13))
    dem = DemSurface(x, y, rng.normal(size=(13, 17)), smoothing=smoothing)
    tx, ty = np.unique(dem.spline.tck[1]), np.unique(dem.spline.tck[0])
    points = [(rng.uniform(x[0], x[-1]), rng.uniform(y[0], y[-1])) for _ in range(500)]
    points += [(a, b) for a in tx for b in ty[::3]]  # on knot lines and corners
    scale = max(1.0, float(np.max(np.abs(dem.z))))
    for p in points:
        compiled = np.array(spline_surface(dem.params, *p)[1:])
        python = np.array(spline_surface.py_func(dem.params, *p)[1:])
        hessian = dem.hessian(p)
        scipy = np.array([dem.height(p), *dem.gradient(p), hessian[0, 0], hessian[0, 1],
                          hessian[1, 1]])
        assert spline_surface(dem.params, *p)[0]
        np.testing.assert_allclose(compiled, scipy, rtol=0, atol=1e-12 * scale)
        np.testing.assert_array_equal(compiled, python)


def test_outside_the_grid_is_not_inside():
    dem = load_dem(HILLS)
    assert not spline_surface(dem.params, -0.01, 5.0)[0]
    assert not spline_surface(dem.params, 5.0, 40.01)[0]
    assert not dem.contains((50.5, 3.0))
    with pytest.raises(ValueError, match="outside the DEM grid"):
        dem.height((51.0, 3.0))


def test_rod_ends_across_knot_lines_match_a_restarted_reference():
    """Rods crossing several 2 m knot cells agree with DOP853 restarted at every knot line."""
    from tests.dem_reference import make_cases, reference_rod_end

    dem = load_dem(HILLS)
    crossed = 0
    for p, heading, n in make_cases(dem, 8, SPACING, SEED):
        end, _ = rod_end(dem, p, heading, SPACING)
        reference, crossings = reference_rod_end(dem, p, n, SPACING)
        crossed += crossings
        assert np.max(np.abs(end - reference)) < 1e-8  # design: 1e-6 on a DEM, 1e-8 in general
    assert crossed >= 8  # the rods do cross knot lines


def test_geodesic_leaving_the_grid_raises():
    dem = load_dem(HILLS)
    with pytest.raises(SurfaceDomainError):
        integrate_geodesic(dem, (45.0, 20.0), (1.0, 0.0), 10.0)


# ------------------------------------------------------------------ refused input

def test_no_data_cells_are_refused(tmp_path):
    z = hills_heights().astype(np.float64)
    z[3, 4] = -9999.0
    path = write_ascii(tmp_path / "holes.asc", z, HILLS_CELL, nodata=-9999.0)
    with pytest.raises(ValueError, match="no-data cell.*column 4, row 3.*python -m swarm "
                                         "dem-crop"):  # the way out is named
        load_dem(path)


# ------------------------------------------------------------------ cropping no-data away

@pytest.mark.parametrize("min_side", [1, 3])
def test_largest_rectangle_is_the_brute_force_one(min_side):
    rng = np.random.default_rng(SEED)
    for _ in range(200):
        rows, cols = rng.integers(1, 9, size=2)
        valid = rng.random((rows, cols)) < rng.uniform(0.3, 0.95)
        best = 0
        for j0 in range(rows):
            for j1 in range(j0 + min_side, rows + 1):
                for i0 in range(cols):
                    for i1 in range(i0 + min_side, cols + 1):
                        if valid[j0:j1, i0:i1].all():
                            best = max(best, (j1 - j0) * (i1 - i0))
        j0, j1, i0, i1 = largest_rectangle(valid, min_side)
        assert (j1 - j0) * (i1 - i0) == best, valid
        if best:
            assert valid[j0:j1, i0:i1].all() and min(j1 - j0, i1 - i0) >= min_side


def _holey_hills(nodata: float) -> np.ndarray:
    """The hills heights (south row first) with no-data nodes along two edges and inside."""
    z = hills_heights().astype(np.float64)
    z[:2, :] = nodata  # the two southern rows
    z[:, -3:] = nodata  # the three eastern columns
    z[15, 5] = nodata  # one hole in the middle
    return z


@pytest.mark.parametrize("kind", ["geotiff", "ascii", "geographic"])
def test_dem_crop_keeps_the_largest_rectangle_with_data(tmp_path, kind):
    z = _holey_hills(-9999.0)
    if kind == "ascii":
        source = write_ascii(tmp_path / "holes.asc", z, HILLS_CELL, nodata=-9999.0)
    else:
        crs, cell = (HILLS_CRS, HILLS_CELL) if kind == "geotiff" else ("EPSG:4326", 1e-4)
        source = write_geotiff(tmp_path / "holes.tif", np.ma.masked_equal(z, -9999.0)
                               .filled(np.nan).astype(np.float32), west=1.0, south=50.0,
                               cell_x=cell, cell_y=cell, crs=crs)
    crop = crop_dem(source, tmp_path / "out" / "crop.tif")
    x, y, heights = read_grid(source)
    valid = np.isfinite(heights)
    (i0, i1), (j0, j1) = crop.columns, crop.rows
    assert valid[j0:j1 + 1, i0:i1 + 1].all()
    assert (j1 - j0 + 1) * (i1 - i0 + 1) == np.prod(np.subtract(largest_rectangle(valid, 4)[1::2],
                                                                largest_rectangle(valid, 4)[::2]))
    assert crop.dropped == int((~valid).sum())
    assert crop.origin == (x[i0], y[j0])
    cx, cy, cz = read_dem(crop.path)  # loads: no no-data left
    np.testing.assert_array_equal(cz, heights[j0:j1 + 1, i0:i1 + 1])
    if kind != "geographic":  # metres: the crop's frame is the source's, shifted
        np.testing.assert_allclose(cx, x[i0:i1 + 1] - x[i0], atol=1e-9)
        np.testing.assert_allclose(cy, y[j0:j1 + 1] - y[j0], atol=1e-9)
    import rasterio

    with rasterio.open(source) as src, rasterio.open(crop.path) as dst:
        assert dst.crs == src.crs and dst.res == pytest.approx(src.res)
        # the crop's south-west node is where the source's node (i0, j0) is on the ground
        north_up = src.transform.e < 0
        row = src.height - 1 - j0 if north_up else j0
        np.testing.assert_allclose(dst.xy(dst.height - 1, 0), src.xy(row, i0), rtol=1e-12)


def test_dem_crop_bounds_keep_the_nodes_inside(tmp_path):
    z = _holey_hills(-9999.0)
    source = write_ascii(tmp_path / "holes.asc", z, HILLS_CELL, nodata=-9999.0)
    x, y, heights = read_grid(source)
    crop = crop_dem(source, tmp_path / "box.tif", bounds=(x[2], y[3], x[9] + 0.5, y[12]))
    assert crop.columns == (2, 9) and crop.rows == (3, 12)
    np.testing.assert_array_equal(read_dem(crop.path)[2], heights[3:13, 2:10])
    with pytest.raises(ValueError, match="1 no-data node"):  # the hole at column 5, row 15
        crop_dem(source, tmp_path / "bad.tif", bounds=(x[2], y[10], x[9], y[20]))
    with pytest.raises(ValueError, match="at least 4 × 4"):
        crop_dem(source, tmp_path / "bad.tif", bounds=(x[2], y[3], x[4], y[12]))
    with pytest.raises(ValueError, match="xmin < xmax"):
        crop_dem(source, tmp_path / "bad.tif", bounds=(x[9], y[3], x[2], y[12]))
    with pytest.raises(ValueError, match="is the source DEM"):
        crop_dem(source, source)
    before = crop.path.read_bytes()
    with pytest.raises(ValueError, match="exists; choose another path or replace it"):
        crop_dem(source, crop.path)  # nothing is overwritten unasked
    assert crop.path.read_bytes() == before
    assert crop_dem(source, crop.path, force=True).rows == (2, 20)  # the largest rectangle
    with pytest.raises(ValueError, match="GeoTIFF"):
        crop_dem(source, tmp_path / "out.asc")
    assert not (tmp_path / "bad.tif").exists()


def test_dem_crop_refuses_a_dem_without_a_4x4_rectangle_of_data(tmp_path):
    z = hills_heights().astype(np.float64)
    z[::3, :] = -9999.0  # every third row: at most 2 rows of data in a row
    source = write_ascii(tmp_path / "striped.asc", z, HILLS_CELL, nodata=-9999.0)
    with pytest.raises(ValueError, match="no rectangle of 4 × 4 nodes holds data"):
        crop_dem(source, tmp_path / "crop.tif")


def test_dem_crop_command(tmp_path, capsys):
    from swarm.cli import main

    source = write_ascii(tmp_path / "holes.asc", _holey_hills(-9999.0), HILLS_CELL,
                         nodata=-9999.0)
    assert main(["dem-crop", str(source), str(tmp_path / "crop.tif")]) == 0
    out = capsys.readouterr().out
    # the hole at column 5, row 15 leaves columns 6-22 over rows 2-20 the largest rectangle
    assert "columns 6–22, rows 2–20 from the south" in out
    assert f"origin at ({6 * HILLS_CELL:g}, {2 * HILLS_CELL:g}) m" in out
    assert main(["dem-crop", str(source), str(tmp_path / "c.tif"), "--bounds", "0,0,10,10"]) == 2
    assert "no-data node" in capsys.readouterr().err
    with pytest.raises(SystemExit) as stop:
        main(["dem-crop", str(source), str(tmp_path / "c.tif"), "--bounds", "0,0,nan,1"])
    assert stop.value.code == 2
    assert "four finite numbers" in capsys.readouterr().err


def test_unknown_crs_units_are_refused(tmp_path):
    path = write_geotiff(tmp_path / "feet.tif", hills_heights(), west=6_000_000.0,
                         south=2_000_000.0, cell_x=6.0, cell_y=6.0, crs="EPSG:2227")
    with pytest.raises(ValueError, match="linear unit"):
        load_dem(path)


def test_grids_too_small_for_a_bicubic_spline_are_refused(tmp_path):
    path = write_geotiff(tmp_path / "small.tif", np.ones((3, 6)), west=0.0, south=0.0,
                         cell_x=1.0, cell_y=1.0, crs=HILLS_CRS)
    with pytest.raises(ValueError, match="too small for a bicubic spline"):
        load_dem(path)


@pytest.mark.parametrize("name, params, message", [
    ("dem:", {}, "dem:PATH"),
    ("dem:/no/such/file.tif", {}, "no such DEM file"),
    (f"dem:{HILLS}", {"smoothing": -1.0}, "smoothing must be"),
    (f"dem:{HILLS}", {"sigma": 1.0}, "not parameters of a DEM"),
])
def test_bad_dem_references_are_refused(name, params, message):
    with pytest.raises(ValueError, match=message):
        make_surface(name, params)


def test_a_dem_needs_a_leader_start_on_its_grid():
    from world.main import resolve_with_surface

    config = RunConfig(surface=f"dem:{HILLS}")
    with pytest.raises(ValueError, match="no default leader start"):
        resolve_with_surface(config)
    with pytest.raises(ValueError, match=r"\(80, 8\) lies outside the DEM grid x ∈ \[0, 50\]"):
        resolve_with_surface(config.replace(leader_start=(80.0, 8.0, 1.0, 0.0)))


def test_cli_smoothing_flag_sets_the_surface_parameter():
    from swarm.cli import build_parser, config_from_args

    args = build_parser().parse_args(["run", "--surface", f"dem:{HILLS}", "--smoothing", "3",
                                      "--leader-start", "6,8,1,0"])
    config = config_from_args(args)
    assert config.surface_params == {"smoothing": 3.0}
    assert config.leader_start == (6.0, 8.0, 1.0, 0.0)


def test_committed_dem_is_what_the_script_makes():
    assert HILLS.stat().st_size < 8_000
    np.testing.assert_array_equal(load_dem(HILLS).z, hills_heights().astype(np.float64))
    y, x = (np.arange(n) * HILLS_CELL for n in HILLS_SHAPE)
    np.testing.assert_allclose(hills_heights(), hills_function(*np.meshgrid(x, y)), atol=1e-5)


# ------------------------------------------------------------------ runs, figures, experiment

@pytest.fixture(scope="module")
def dem_config() -> RunConfig:
    return RunConfig(run_id="dem-e2e", surface=f"dem:{HILLS}", leader_start=HILLS_LEADER_START,
                     followers=2, ticks=12, estimator="auto", agent_timeout=20.0,
                     noise_range=0.005, noise_move=0.005, seed=SEED % 1000)


@pytest.fixture(scope="module")
def dem_run(tmp_path_factory, dem_config):
    from swarm.launch import launch

    out = tmp_path_factory.mktemp("dem-inproc")
    summary = launch(dem_config, out, in_process=True)
    return out, summary


def _numbers(run_dir: Path) -> tuple[str, dict]:
    summary = json.loads((run_dir / "summary.json").read_text())
    return (run_dir / "ticks.csv").read_text(), summary["followers"]


def test_dem_run_over_zenoh_is_identical_in_every_layout(tmp_path, dem_run, dem_config):
    from swarm.launch import launch
    from swarm.local import run_local

    out, summary = dem_run
    assert summary["complete"] and summary["ticks_completed"] == dem_config.ticks
    assert launch(dem_config, tmp_path / "procs", in_process=False)["complete"]
    assert _numbers(tmp_path / "procs") == _numbers(out)
    run_local(dem_config, tmp_path / "local")
    assert _numbers(tmp_path / "local") == _numbers(out)


def test_dem_run_follows_the_ideal_formation(dem_run, dem_config):
    from protocol.record import read_ticks

    out, _ = dem_run
    truth = ideal_formation(load_dem(HILLS), HILLS_LEADER_START, 2, SPACING, COMM_PERIOD,
                            dem_config.ticks)
    for row in read_ticks(out / "ticks.csv"):
        # follower 1's ideal position is the rod end of the leader, which drives exactly;
        # follower 2's starts where follower 1 really stands (near its place: noise)
        if row["agent"] > 0:
            np.testing.assert_allclose([row["ideal_x"], row["ideal_y"]],
                                       truth[row["agent"], row["tick"]],
                                       atol=1e-9 if row["agent"] == 1 else 0.05)


def test_dem_run_figures_draw_the_hillshade(dem_run):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from swarm.plots import plot_run, terrain_relief

    out, _ = dem_run
    paths = plot_run(out)
    assert all(p.stat().st_size > 10_000 for p in paths)
    fig = Figure()
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    image, contours = terrain_relief(ax, load_dem(HILLS), np.array([-5.0, 2.0]),
                                     np.array([30.0, 20.0]))
    shade = image.get_array()
    assert image.get_extent() == [0.0, 30.0, 2.0, 20.0]  # clipped to the grid
    assert 0.0 <= shade.min() < shade.max() <= 1.0 and len(contours.levels) > 3


def test_terrain_experiment_quick(tmp_path):
    from swarm.experiment import read_table
    from swarm.terrain import TerrainSpec, quick, run_terrain_experiment

    spec = quick(TerrainSpec((HILLS_LEADER_START,), estimators=("persist", "edmd-b"),
                             spacing=SPACING))
    result = run_terrain_experiment(HILLS, tmp_path, spec, workers=1, progress=False)
    assert not result["failed"] and not result["figure_problems"]
    comm = read_table(result["tables"]["terrain_comm_period"])
    assert [(r["start"], r["comm_period"], r["estimator"]) for r in comm] == [
        (0, p, e) for p in spec.comm_periods for e in spec.estimators]
    position = read_table(result["tables"]["terrain_position"])
    assert {r["follower"] for r in position} == {1, 2}
    assert all(r["mean_required_range"] > 0 for r in comm + position)
    report = result["report"].read_text()
    edmd = next(r for r in comm if r["estimator"] == "edmd-b")["mean_required_range"]
    assert f"{edmd:.3g}" in report


def test_terrain_spec_needs_a_leader_start_and_known_periods():
    from swarm.cli import main
    from swarm.terrain import TerrainSpec

    with pytest.raises(ValueError, match="position_periods"):
        TerrainSpec(((1.0, 2.0, 1.0, 0.0),), comm_periods=(0.5,), position_periods=(1.28,))
    with pytest.raises(ValueError, match="at least one start"):
        TerrainSpec(())
    assert main(["experiment", "terrain", "--dem", str(HILLS)]) == 2
    assert main(["experiment", "terrain", "--dem", str(HILLS), "--leader-start", "6,8,1"]) == 2
    assert main(["experiment", "terrain", "--dem", str(HILLS), "--leader-start", "90,8,1,0",
                 "--quick"]) == 2  # off the grid: refused before any run


def test_mean_over_starts_never_hides_a_failed_run():
    from swarm.terrain import mean_over_starts

    rows = [{"start": 0, "comm_period": 1.28, "estimator": "persist", "mean_required_range": 1.0},
            {"start": 1, "comm_period": 1.28, "estimator": "persist", "mean_required_range": 3.0},
            {"start": 0, "comm_period": 1.28, "estimator": "auto", "mean_required_range": 0.5},
            {"start": 1, "comm_period": 1.28, "estimator": "auto",
             "mean_required_range": math.nan}]
    means = mean_over_starts(rows, ("comm_period", "estimator"))
    assert means[0] == {"comm_period": 1.28, "estimator": "persist", "starts": 2,
                        "mean_required_range": 2.0}
    assert math.isnan(means[1]["mean_required_range"])


def _uneven_grid(seed: int) -> tuple[np.ndarray, np.ndarray, np.random.Generator]:
    """Node coordinates of a 20 × 16 grid with 0.5–2.5 m spacing, and the generator after."""
    rng = np.random.default_rng(seed)
    return (np.concatenate([[0.0], np.cumsum(rng.uniform(0.5, 2.5, 19))]),
            np.concatenate([[0.0], np.cumsum(rng.uniform(0.5, 2.5, 15))]), rng)


@pytest.mark.parametrize("kind", ["steep", "smoothed"])
def test_rod_ends_on_unseen_terrain_match_the_reference(kind):
    """Terrain the code was not tuned on, on an uneven 0.5–2.5 m grid: random heights
    (slopes of several units, interpolated), or a smooth field with noise fitted by a
    smoothing spline (fewer, uneven knots)."""
    from tests.dem_reference import make_cases, reference_rod_end

    x, y, rng = _uneven_grid(SEED + 1)
    if kind == "steep":
        dem = DemSurface(x, y, 2.0 * rng.normal(size=(16, 20)))
    else:
        z = 3.0 * np.sin(x / 4)[None, :] * np.cos(y / 5)[:, None]
        dem = DemSurface(x, y, z + 0.05 * rng.normal(size=z.shape), smoothing=3.0)
    for p, heading, n in make_cases(dem, 4, 5.0, SEED):
        end, _ = rod_end(dem, p, heading, 5.0)
        reference, _ = reference_rod_end(dem, p, n, 5.0)
        assert np.max(np.abs(end - reference)) < 1e-8


def test_a_failed_smoothing_fit_is_refused():
    """scipy 1.17 returns unsorted knots for this grid at s = 100 (no B-spline at all)."""
    from scipy.interpolate import RectBivariateSpline

    x, y, rng = _uneven_grid(SEED + 1)
    z = 2.0 * rng.normal(size=(16, 20))
    knots = RectBivariateSpline(y, x, z, s=100.0).tck[:2]
    if all(np.all(np.diff(t) >= 0) for t in knots):
        pytest.skip("this scipy fits this grid with sorted knots")
    with pytest.raises(ValueError, match="smoothing = 100 .* unsorted knots"):
        DemSurface(x, y, z, smoothing=100.0)


def test_a_dem_deep_in_a_folder_tree_gets_a_view_map(tmp_path):
    """The config takes a DEM path of up to 4096 characters, the view's texts 256: the map
    shows the path's end instead of refusing the run's view."""
    import shutil

    from protocol.view import MAX_VIEW_TEXT, decode_map, encode_map
    from world.main import resolve_with_surface
    from world.sim import WorldSim
    from world.view import map_payload

    deep = tmp_path.joinpath(*["a-rather-long-folder-name-" + str(i) for i in range(12)])
    deep.mkdir(parents=True)
    path = deep / HILLS.name
    shutil.copyfile(HILLS, path)
    assert len(f"dem:{path}") > MAX_VIEW_TEXT
    config, surface = resolve_with_surface(RunConfig(surface=f"dem:{path}", followers=2,
                                                     leader_start=HILLS_LEADER_START, ticks=6))
    shown = decode_map(encode_map(map_payload(config, surface, WorldSim(config, surface).ideal)))
    assert len(shown["surface"]) == MAX_VIEW_TEXT and shown["relief"] == "dem"
    assert shown["surface"].startswith("dem:…") and shown["surface"].endswith(str(path)[-100:])
