"""Grids beyond one machine: ``swarm sweep --scheduler ADDRESS`` runs each run as one task on
a dask cluster (here a ``LocalCluster`` of 2 worker processes) with the numbers of the local
pool, and an interrupted sweep resumes without running its finished runs again."""
from __future__ import annotations

import os

import pytest

from swarm.cli import main
from swarm.grid import read_table

GRID = """
name = "tiny"
[base]
ticks = 8
surface = "wavy"
noise_range = 0.01
[axes]
estimator = ["persist", "auto"]
seed = [0, 1]
"""
RESULTS = ("ticks.csv", "observations.csv")


def _run_files(out) -> dict[str, bytes]:
    return {f"{row['run']}/{name}": (out / "runs" / row["run"] / name).read_bytes()
            for row in read_table(out / "tables" / "tiny.csv") for name in RESULTS}


@pytest.fixture(scope="module")
def cluster():
    distributed = pytest.importorskip("distributed")  # here, not at import: only these tests
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None,
                                  env={"PYTHONPATH": os.environ.get("PYTHONPATH", "")}) as c:
        yield c


@pytest.fixture(scope="module")
def local_sweep(tmp_path_factory):
    folder = tmp_path_factory.mktemp("local")
    (folder / "tiny.toml").write_text(GRID)
    assert main(["sweep", str(folder / "tiny.toml"), "--out", str(folder / "out"),
                 "--workers", "1"]) == 0
    return folder / "out"


@pytest.mark.slow  # a dask cluster; fast tier: the local pool's sweeps (test_sweep.py) and the
# unreachable scheduler below
def test_sweep_on_a_dask_cluster_matches_the_local_pool(tmp_path, cluster, local_sweep):
    grid = tmp_path / "tiny.toml"
    grid.write_text(GRID)
    out = tmp_path / "out"
    assert main(["sweep", str(grid), "--out", str(out), "--scheduler",
                 cluster.scheduler_address]) == 0
    assert _run_files(out) == _run_files(local_sweep)
    assert (read_table(out / "tables" / "tiny-mean.csv")
            == read_table(local_sweep / "tables" / "tiny-mean.csv"))
    index = read_table(out / "tables" / "runs.csv")
    assert len(index) == 4 and {r["status"] for r in index} == {"ok"}


@pytest.mark.slow  # a dask cluster, as above
def test_an_interrupted_sweep_resumes_without_redoing_finished_runs(tmp_path, cluster,
                                                                    local_sweep):
    grid = tmp_path / "tiny.toml"
    grid.write_text(GRID)
    out = tmp_path / "out"
    assert main(["sweep", str(grid), "--out", str(out), "--workers", "1"]) == 0
    runs = [row["run"] for row in read_table(out / "tables" / "tiny.csv")]
    # as an interruption leaves it: one run never started, one stopped halfway
    import shutil

    shutil.rmtree(out / "runs" / runs[0])
    (out / "runs" / runs[1] / "summary.json").unlink()
    (out / "runs" / runs[1] / "ticks.csv").write_text("tick\n")
    kept = {r: (out / "runs" / r / "ticks.csv").stat().st_mtime_ns for r in runs[2:]}
    assert main(["sweep", str(grid), "--out", str(out), "--scheduler",
                 cluster.scheduler_address]) == 0
    attempts = {row["run"]: row["attempts"] for row in read_table(out / "tables" / "runs.csv")}
    assert [attempts[r] for r in runs] == [1, 1, 0, 0]
    assert {r: (out / "runs" / r / "ticks.csv").stat().st_mtime_ns for r in runs[2:]} == kept
    assert _run_files(out) == _run_files(local_sweep)


def test_an_unreachable_scheduler_is_one_line(tmp_path, capsys):
    from protocol.session import free_tcp_endpoint

    grid = tmp_path / "tiny.toml"
    grid.write_text(GRID)
    address = "tcp://" + free_tcp_endpoint().split("/", 1)[1]
    dask = pytest.importorskip("dask")
    # dask's own connect timeout (30 s by default), shortened: nothing listens there
    with dask.config.set({"distributed.comm.timeouts.connect": "2s"}):
        assert main(["sweep", str(grid), "--out", str(tmp_path / "out"), "--scheduler",
                     address]) == 2
    assert "cannot reach the dask scheduler" in capsys.readouterr().err
