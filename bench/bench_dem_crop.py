"""Benchmark ``python -m swarm dem-crop`` on an SRTM-sized DEM with no-data along its edges.

Writes an ``N × N`` float32 GeoTIFF (default 3601, one SRTM 1-arc-second tile) whose western
columns and northern rows hold no data, with scattered holes, then in a child process each
(so that peak memory is the command's own): crops it (:func:`swarm.terrain.crop_dem`, the
largest rectangle with data) and loads the crop as a surface (the spline fit a run does).
Prints wall times, peak resident memory, and their ratios to the raster's size in memory.

Run ``python bench/bench_dem_crop.py [--size N]``.
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

from swarm.terrain import write_geotiff  # noqa: E402  (after the path set-up)

STEPS = {
    "crop": "from swarm.terrain import crop_dem; crop_dem({src!r}, {out!r})",
    "load the crop": "from world.dem import load_dem; load_dem({out!r})",
}


def make_dem(path: Path, size: int, seed: int = 0) -> int:
    """A smooth random DEM (metres, 30 m cells, UTM) with no-data edges and holes; returns
    how many nodes hold no data."""
    rng = np.random.default_rng(seed)
    x = np.linspace(0.0, 1.0, size, dtype=np.float32)
    z = 500.0 + 300.0 * np.sin(7.0 * x)[None, :] * np.cos(5.0 * x)[:, None]
    z[-size // 20:, :] = np.nan  # northern rows (south row first here)
    z[:, : size // 30] = np.nan  # western columns
    holes = rng.integers(0, size, size=(20, 2))
    z[holes[:, 0], holes[:, 1]] = np.nan
    write_geotiff(path, z, west=500_000.0, south=4_000_000.0, cell_x=30.0, cell_y=30.0,
                  crs="EPSG:32616")
    return int(np.isnan(z).sum())


def run_step(code: str) -> tuple[float, float]:
    """Wall seconds and peak resident MB of ``code`` in a fresh interpreter (imports
    included, so this is what the command costs), as that interpreter measures itself."""
    report = "; import resource; print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)"
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-c", code + report], cwd=REPO_ROOT, check=True,
                          capture_output=True, text=True)
    wall = time.perf_counter() - start
    return wall, int(done.stdout.split()[-1]) / 1024.0  # ru_maxrss is in KiB on Linux


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=3601, help="nodes along each axis")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        src, out = Path(folder) / "dem.tif", Path(folder) / "crop.tif"
        missing = make_dem(src, args.size)
        raster_mb = args.size**2 * 8 / 2**20  # as float64, the reader's working copy
        print(f"{args.size} × {args.size} nodes, {missing} without data; "
              f"{raster_mb:.0f} MB as float64")
        print(f"{'step':<16}{'wall s':>8}{'peak MB':>9}{'peak / raster':>15}")
        for label, code in STEPS.items():
            wall, peak = run_step(code.format(src=str(src), out=str(out)))
            print(f"{label:<16}{wall:>8.2f}{peak:>9.0f}{peak / raster_mb:>15.1f}")


if __name__ == "__main__":
    main()
