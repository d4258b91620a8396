"""The small DEM committed for the tests, ``tests/data/hills.tif``, and how it was made.

``python tests/make_dem_data.py`` rewrites it; ``tests/test_dem.py`` checks that the committed
file holds exactly :func:`hills_heights`. The grid is 26 × 21 nodes at 2 m (50 m × 40 m) in a
projected CRS (UTM zone 32N, EPSG:32632), heights float32 in metres: a hill, a tilt and a
gentle wave, so the column climbs, turns and crosses many knot lines within a short run.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

REPO_ROOT = Path(__file__).resolve().parents[1]
HILLS = REPO_ROOT / "tests" / "data" / "hills.tif"
HILLS_CELL = 2.0
HILLS_SHAPE = (21, 26)  # rows (south to north), columns
HILLS_CRS = "EPSG:32632"
HILLS_ORIGIN = (500_000.0, 5_200_000.0)  # west and south edges (m)
HILLS_LEADER_START = (6.0, 8.0, 1.0, 0.0)


def hills_function(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Height (m) at design-frame coordinates ``x``, ``y`` (m) of the test terrain."""
    return (4.0 * np.exp(-((x - 20.0) ** 2 + (y - 18.0) ** 2) / 150.0) + 0.05 * x
            + 1.5 * np.sin(x / 9.0) * np.cos(y / 11.0))


def hills_heights() -> np.ndarray:
    """The committed heights, shape (21, 26), south row first, float32."""
    y, x = (np.arange(n) * HILLS_CELL for n in HILLS_SHAPE)
    return hills_function(*np.meshgrid(x, y)).astype(np.float32)


def main() -> None:
    if str(REPO_ROOT) not in sys.path:
        sys.path.insert(0, str(REPO_ROOT))
    from swarm.terrain import write_geotiff

    write_geotiff(HILLS, hills_heights(), west=HILLS_ORIGIN[0], south=HILLS_ORIGIN[1],
                  cell_x=HILLS_CELL, cell_y=HILLS_CELL, crs=HILLS_CRS)
    print(f"wrote {HILLS} ({HILLS.stat().st_size} bytes)")


if __name__ == "__main__":
    main()
