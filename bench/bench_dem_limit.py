"""Memory per cell of loading a DEM (the figure behind ``world.dem.BYTES_PER_CELL`` and
``MAX_CELLS``) and of ``dem-crop`` (behind ``swarm.terrain.CROP_MAX_CELLS``), and what a refused
raster costs.

For each size, a smooth ``N × N`` float32 GeoTIFF is written, then each step runs in a fresh
interpreter that reports its resident memory after its imports and at its peak: the
difference over the cells is the step's own memory per cell. Last, a few-kilobyte sparse
GeoTIFF whose header claims 200000 × 200000 cells is loaded: the time and memory of the
refusal.

Run ``python bench/bench_dem_limit.py [--sizes 1000,2000,3000]``.
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import rasterio
from rasterio.transform import Affine

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

from swarm.terrain import write_geotiff  # noqa: E402  (after the path set-up)

MEASURE = """
import resource, sys, time
{imports}
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
start = time.perf_counter()
try:
    {call}
    outcome = "loaded"
except Exception as exc:
    outcome = type(exc).__name__
wall = time.perf_counter() - start
print(before, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, wall, outcome)
"""
STEPS = {
    "load (run)": ("from world.dem import load_dem", "load_dem({src!r})"),
    "dem-crop": ("from swarm.terrain import crop_dem", "crop_dem({src!r}, {out!r}, force=True)"),
}


def measure(imports: str, call: str) -> tuple[float, float, float, str]:
    """(resident KiB after the imports, peak KiB, wall s, outcome) of ``call`` in a fresh
    interpreter."""
    done = subprocess.run([sys.executable, "-c", MEASURE.format(imports=imports, call=call)],
                          cwd=REPO_ROOT, check=True, capture_output=True, text=True)
    before, peak, wall, outcome = done.stdout.split()
    return float(before), float(peak), float(wall), outcome


def write_dem(path: Path, size: int) -> None:
    x = np.linspace(0.0, 6.0, size, dtype=np.float32)
    z = 100.0 * np.sin(x)[None, :] * np.cos(0.7 * x)[:, None]
    write_geotiff(path, z, west=0.0, south=0.0, cell_x=10.0, cell_y=10.0, crs="EPSG:32632")


def write_huge_header(path: Path, side: int = 200_000) -> None:
    """A tiled, sparse GeoTIFF claiming ``side`` × ``side`` float32 cells, no tile written."""
    with rasterio.open(path, "w", driver="GTiff", width=side, height=side, count=1,
                       dtype="float32", crs="EPSG:32632",
                       transform=Affine(1, 0, 0, 0, -1, side), tiled=True, blockxsize=8192,
                       blockysize=8192, compress="deflate", BIGTIFF="YES", SPARSE_OK="TRUE"):
        pass


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="1000,2000,3000", help="nodes along each axis")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        print(f"{'step':<12}{'cells':>12}{'own MB':>9}{'bytes/cell':>12}{'wall s':>8}")
        for size in (int(s) for s in args.sizes.split(",")):
            src, out = Path(folder) / f"dem-{size}.tif", Path(folder) / "crop.tif"
            write_dem(src, size)
            for label, (imports, call) in STEPS.items():
                before, peak, wall, _ = measure(imports, call.format(src=str(src),
                                                                     out=str(out)))
                own = (peak - before) * 1024.0
                print(f"{label:<12}{size * size:>12,}{own / 2**20:>9.0f}"
                      f"{own / size**2:>12.1f}{wall:>8.2f}")
        huge = Path(folder) / "huge.tif"
        write_huge_header(huge)
        start = time.perf_counter()
        before, peak, wall, outcome = measure("from world.dem import load_dem",
                                              f"load_dem({str(huge)!r})")
        print(f"a {huge.stat().st_size / 1024:.0f} KiB GeoTIFF claiming 200000 × 200000 cells: "
              f"{outcome} after {wall * 1000:.1f} ms, {(peak - before) / 1024:.1f} MB of its "
              f"own (the interpreter: {peak / 1024:.0f} MB; whole child "
              f"{time.perf_counter() - start:.1f} s with imports)")


if __name__ == "__main__":
    main()
