"""``python -m swarm sweep GRID.toml`` and ``python -m swarm compare``: grids of runs over Zenoh
(surfaces × estimators × comm periods × seeds × noise, or any other options), one table.

A grid file::

    name = "noisy"                  # table name (default: the file's stem)
    follower = 1                    # whose metrics the table shows (default 1)

    [base]                          # options every run shares (any `swarm run` option)
    ticks = 40

    [axes]                          # in this order; the last varies fastest
    surface = ["elliptic", "wavy"]
    estimator = ["persist", "edmd-b", "kalman", "auto"]   # edmd-<letter>, built-in or pkg.mod:Name
    comm_period = [0.64, 1.28]
    seed = [0, 1, 2]

    [axes.noise]                    # a table: label = the options it sets
    none = {}
    middle = { noise_range = 0.02, noise_bearing = 0.01 }

``compare`` is the grid ``estimator × seed`` around one setup given by ``swarm run``'s flags.
Both run every configuration with :func:`swarm.grid.run_grid` (the world as embedded router,
every agent its own Zenoh session), write ``D/runs/<name>/…``, ``D/tables/<name>.csv`` (one row
per run), ``D/tables/<name>-mean.csv`` (averaged over the seeds) and ``D/tables/runs.csv``,
and print the mean table with each estimator's ratio to the persist baseline of the same runs.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

from protocol.config import MAX_CONFIG_DEPTH, read_toml
from swarm.grid import (
    SUMMARY_COLUMNS,
    Axis,
    RunOutcome,
    estimator_axis,
    expand,
    mean_over,
    run_grid,
    summary_row,
    table_number,
    write_run_index,
    write_table,
)

GRID_DEPTH = MAX_CONFIG_DEPTH + 2  # a run's options, under [axes.<axis>.<label>]


def axis_from_toml(name: str, value: Any) -> Axis:
    """An axis of a grid file: a list of values of option ``name`` (estimator labels for
    ``estimator``), or a table of labelled option sets."""
    if isinstance(value, dict):
        for label, options in value.items():
            if not isinstance(options, dict):
                raise ValueError(f"axes.{name}.{label} must be a table of options")
        return Axis(name, tuple(value.items()))
    if not isinstance(value, list) or not value:
        raise ValueError(f"axes.{name} must be a non-empty list or a table")
    if name == "estimator":
        return estimator_axis(value)
    fragment = {"comm_period": "tc{:g}", "seed": "s{}"}.get(name, "{}")
    return Axis.of_field(name, value, fragment)


def load_grid(path: str | Path) -> tuple[str, dict[str, Any], list[Axis], int]:
    """Read a grid file: (table name, base options, axes, follower). ValueError names
    problems."""
    path = Path(path)
    data = read_toml(path, "grid file", GRID_DEPTH)
    unknown = set(data) - {"name", "follower", "base", "axes"}
    if unknown:
        raise ValueError(f"grid file {path}: unknown key(s) {sorted(unknown)}")
    name = data.get("name", path.stem)
    follower = data.get("follower", 1)
    axes_data = data.get("axes")
    if not isinstance(axes_data, dict) or not axes_data:
        raise ValueError(f"grid file {path}: [axes] must name at least one axis")
    base = data.get("base", {})
    try:
        if not isinstance(base, dict):
            raise ValueError("[base] must be a table of options")
        axes = [axis_from_toml(k, v) for k, v in axes_data.items()]
        runs = expand(name, base, axes)  # every combination must be a valid configuration
    except (TypeError, ValueError) as exc:
        raise ValueError(f"grid file {path}: {exc}") from None
    followers = min(run.config.followers for run in runs)
    if not isinstance(follower, int) or not 1 <= follower <= followers:
        raise ValueError(f"grid file {path}: follower must be in 1..{followers}")
    return name, base, axes, follower


def compare_axes(estimators: list[str], seeds: list[int]) -> list[Axis]:
    """The axes of ``swarm compare``: the estimators, then the seeds."""
    if not estimators:
        raise ValueError("--estimators must name at least one estimator")
    return [estimator_axis(estimators),
            Axis.of_field("seed", seeds, "s{}")]


def run_sweep(name: str, base: dict[str, Any], axes: list[Axis], out_dir: str | Path,
              follower: int = 1, workers: int | None = None, progress: bool = True,
              scheduler: str | None = None) -> dict:
    """Run the grid (on the dask scheduler at ``scheduler`` if given; runs already finished
    in ``out_dir`` are kept), write its tables; returns ``rows``, ``means``, ``outcomes``,
    ``tables``."""
    out_dir = Path(out_dir)
    runs = expand(name, base, axes)
    outcomes: list[RunOutcome] = run_grid(runs, out_dir / "runs", workers=workers,
                                          progress=progress, scheduler=scheduler)
    keys = tuple(axis.name for axis in axes)
    rows = [summary_row(o, follower) for o in outcomes]
    columns = keys + SUMMARY_COLUMNS + ("run",)
    tables = {"runs": out_dir / "tables" / f"{name}.csv",
              "mean": out_dir / "tables" / f"{name}-mean.csv"}
    write_table(tables["runs"], columns, rows)
    mean_keys = tuple(k for k in keys if k != "seed")
    means = mean_over(rows, "seed", mean_keys) if "seed" in keys else rows
    write_table(tables["mean"], mean_keys + SUMMARY_COLUMNS + (("n", "seed") if "seed" in keys
                                                                  else ("run",)), means)
    write_run_index(out_dir / "tables" / "runs.csv", outcomes)
    return {"rows": rows, "means": means, "outcomes": outcomes, "tables": tables,
            "keys": mean_keys}


def format_means(means: list[dict], keys: tuple[str, ...]) -> str:
    """The printed table: key columns, required range, persist from the same readings, the
    ratio, the noise-free persist counterfactual, fallback ticks."""
    head = [*keys, "required", "persist", "ratio", "persist (noise-free)", "fallback"]
    body = [[str(row[k]) for k in keys] + [
        table_number(row["mean_required_range"], 5), table_number(row["mean_persist_range"], 5),
        table_number(row["ratio_to_persist"], 3),
        table_number(row["mean_persist_range_noise_free"], 5),
        table_number(row["fallback_ticks"], 1)] for row in means]
    widths = [max(len(h), *(len(r[i]) for r in body)) for i, h in enumerate(head)]
    lines = ["  ".join(h.rjust(w) for h, w in zip(head, widths))]
    lines.append("-" * len(lines[0]))
    lines += ["  ".join(c.rjust(w) for c, w in zip(r, widths)) for r in body]
    lines.append("ratio = required / persist, persist computed from the same noisy readings "
                 "(design §6); below 1 beats persist")
    return "\n".join(lines)

