"""Bounded rasters (design §8): a DEM whose header claims more cells than the limit is refused
before any of its data is read, in one line naming its size and dem-crop, with exit status 2,
and its memory never taken; ``surface_params.max_cells`` moves the limit."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import rasterio
from rasterio.transform import Affine

import swarm.cli
from protocol.config import RunConfig, dump_config
from world.dem import MAX_CELLS, RasterTooLarge, load_dem, make_dem_surface

ROOT = Path(__file__).resolve().parents[1]
HILLS = ROOT / "tests" / "data" / "hills.tif"  # 26 × 21 cells
SMALL_MEMORY_KB = 1 << 20  # a refused raster leaves the process under 1 GiB resident


@pytest.fixture(scope="module")
def huge_tif(tmp_path_factory) -> Path:
    """A real GeoTIFF of a few kilobytes whose header claims 200000 × 200000 float32 cells:
    tiled and sparse, no tile ever written (GDAL reads them as no-data)."""
    path = tmp_path_factory.mktemp("huge") / "huge.tif"
    with rasterio.open(path, "w", driver="GTiff", width=200_000, height=200_000, count=1,
                       dtype="float32", crs="EPSG:32632", transform=Affine(1, 0, 0, 0, -1, 200_000),
                       tiled=True, blockxsize=8192, blockysize=8192, compress="deflate",
                       BIGTIFF="YES", SPARSE_OK="TRUE"):
        pass
    assert path.stat().st_size < 64 * 1024
    return path


@pytest.fixture(scope="module")
def huge_asc(tmp_path_factory) -> Path:
    """An ESRI ASCII grid whose header claims 25000 × 25000 cells and holds four values."""
    path = tmp_path_factory.mktemp("huge") / "huge.asc"
    path.write_text("ncols 25000\nnrows 25000\nxllcorner 0\nyllcorner 0\ncellsize 1\n"
                    "NODATA_value -9999\n1 2 3 4\n")
    return path


def _run_measured(args: list[str]) -> tuple[int, str, int]:
    """Run ``python -m swarm ARGS``; its status, stderr and peak resident memory (KiB)."""
    proc = subprocess.Popen([sys.executable, "-m", "swarm", *args], cwd=ROOT,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        err = proc.stderr.read()
        _, status, usage = os.wait4(proc.pid, 0)
    finally:
        if proc.poll() is None and proc.returncode is None:
            proc.kill()
    proc.returncode = os.waitstatus_to_exitcode(status)
    return proc.returncode, err, usage.ru_maxrss


@pytest.mark.parametrize("raster", ["huge_tif", "huge_asc"])
def test_a_huge_raster_is_refused_before_its_data_is_read(request, tmp_path, raster):
    path = request.getfixturevalue(raster)
    size = "200000 × 200000" if raster == "huge_tif" else "25000 × 25000"
    status, err, peak_kb = _run_measured(["run", "--in-process", "--surface", f"dem:{path}",
                                          "--leader-start", "10,10,1,0",
                                          "--out", str(tmp_path / "out")])
    assert status == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith(f"error: path {str(path)!r}: a {size} raster"), lines[0]
    assert f"over the limit of {MAX_CELLS:,} cells (surface_params.max_cells raises it)" in lines[0]
    assert f"python -m swarm dem-crop {path} OUT.tif" in lines[0]
    assert peak_kb < SMALL_MEMORY_KB, f"{peak_kb} KiB resident"
    assert not (tmp_path / "out" / "ticks.csv").exists()


def test_dem_crop_has_its_own_limit(huge_tif, tmp_path, capsys):
    assert swarm.cli.main(["dem-crop", str(huge_tif), str(tmp_path / "crop.tif")]) == 2
    line = capsys.readouterr().err.strip()
    assert "a 200000 × 200000 raster" in line and "(dem-crop --max-cells raises it)" in line
    assert swarm.cli.main(["dem-crop", str(HILLS), str(tmp_path / "small.tif"),
                           "--max-cells", "100"]) == 2
    assert "a 26 × 21 raster (546 cells" in capsys.readouterr().err
    assert swarm.cli.main(["dem-crop", str(HILLS), str(tmp_path / "small.tif")]) == 0


def test_max_cells_moves_the_limit(tmp_path, capsys):
    with pytest.raises(RasterTooLarge, match="a 26 × 21 raster"):
        make_dem_surface(f"dem:{HILLS}", {"max_cells": 545})
    assert make_dem_surface(f"dem:{HILLS}", {"max_cells": 546}).z.shape == (21, 26)
    assert load_dem(HILLS).z.shape == (21, 26)
    for bad in (0, 1.5, -3):
        with pytest.raises(ValueError, match="surface_params.max_cells must be a whole number"):
            make_dem_surface(f"dem:{HILLS}", {"max_cells": bad})
    config = tmp_path / "run.toml"  # the TOML way, through swarm run
    dump_config(RunConfig(run_id="small-limit", surface=f"dem:{HILLS}",
                          surface_params={"max_cells": 100.0},
                          leader_start=(100.0, 100.0, 1.0, 0.0)), config)
    assert swarm.cli.main(["run", "--in-process", "--config", str(config),
                           "--out", str(tmp_path / "out")]) == 2
    assert "(546 cells" in capsys.readouterr().err


def test_the_refusal_says_what_loading_would_take(huge_tif):
    with pytest.raises(RasterTooLarge, match=r"\(40,000,000,000 cells, 298\.0 GiB as float64, "
                                             r"about 894\.1 GiB to load\)"):
        load_dem(huge_tif)
