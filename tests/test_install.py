"""The core install and its extras (docs/install.md), the console scripts and the one version.

The core's tests run ``python -m swarm`` in processes that see only the core install
(:mod:`tests.block_imports`: every installed distribution outside the closure of
``pyproject.toml``'s ``dependencies`` is refused, as in a fresh environment holding the core).
"""
from __future__ import annotations

import json
import subprocess
import sys
import sysconfig
import tomllib
from importlib import metadata
from pathlib import Path

import pytest

from protocol.config import RunConfig, dump_config
from protocol.distribution import DISTRIBUTION, EXTRAS, missing_extra_message, version
from tests.block_imports import BLOCKED_ENV, core_environment

ROOT = Path(__file__).resolve().parents[1]
PROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]
HILLS = ROOT / "tests" / "data" / "hills.tif"
HEAVY = ("bokeh", "rasterio", "distributed", "dask", "cryptography", "rosbags", "mcap")
SCRIPTS = {"swarm": "swarm.cli:console", "swarm-world": "world.main:console",
           "swarm-leader": "agents.leader:console", "swarm-follower": "agents.follower:console"}
TIMEOUT_S = 120


@pytest.fixture(scope="module")
def core_env(tmp_path_factory) -> dict[str, str]:
    return core_environment(tmp_path_factory.mktemp("core-site"), ROOT)


def _run(env: dict[str, str], *args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *args], env=env, cwd=cwd, capture_output=True,
                          text=True, timeout=TIMEOUT_S)


def test_extras_are_declared_as_the_code_names_them():
    """Every extra the code names (protocol.distribution.EXTRAS) is in pyproject.toml, none of
    the core's packages is heavy, and [test] brings every extra."""
    extras = PROJECT["optional-dependencies"]
    assert set(extras) == set(EXTRAS) | {"test"}
    assert f"{DISTRIBUTION}[{','.join(EXTRAS)}]" in extras["test"]
    core = " ".join(PROJECT["dependencies"])
    assert not any(name in core for name in HEAVY)


def test_the_core_environment_lacks_the_extras_and_the_commands_load_without_them(core_env):
    blocked = set(core_env[BLOCKED_ENV].split(","))
    assert set(HEAVY) <= blocked and "numpy" not in blocked and "zenoh" not in blocked
    proc = _run(core_env, "-c", "import bokeh", cwd=ROOT)
    assert proc.returncode == 1 and "No module named 'bokeh'" in proc.stderr
    modules = ("swarm.cli", "swarm.launch", "swarm.deploy", "swarm.grid", "swarm.experiment",
               "swarm.sweep", "swarm.plots", "swarm.terrain", "swarm.live.store", "world.main",
               "world.dem", "agents.leader", "agents.follower")
    proc = _run(core_env, "-c", f"import sys, {', '.join(modules)}; "
                f"print(sorted(m for m in sys.modules if m.partition('.')[0] in {HEAVY!r}))",
                cwd=ROOT)
    assert proc.returncode == 0 and proc.stdout.strip() == "[]", proc.stderr


@pytest.fixture(scope="module")
def core_runs(core_env, tmp_path_factory) -> dict[str, Path]:
    """The paper's default case, 6 ticks, in-process and as processes, on the core alone."""
    base = tmp_path_factory.mktemp("core-runs")
    runs = {}
    for layout in ("--in-process", "--processes"):
        out = base / layout.strip("-")
        proc = _run(core_env, "-m", "swarm", "run", "--ticks", "6", layout, "--out", str(out),
                    cwd=base)
        assert proc.returncode == 0, proc.stdout + proc.stderr
        runs[layout] = out
    return runs


def test_the_paper_case_runs_on_the_core_in_both_layouts(core_runs):
    inproc, procs = core_runs["--in-process"], core_runs["--processes"]
    for out in (inproc, procs):
        assert json.loads((out / "summary.json").read_text())["complete"] is True
    assert (inproc / "ticks.csv").read_bytes() == (procs / "ticks.csv").read_bytes()
    # the followers' replay logs are gone with their folder once the run is complete
    assert not (procs / "state").exists()


@pytest.mark.slow  # fast tier: the paper case on the core; `swarm plot` in the full install
def test_plot_runs_on_the_core(core_env, core_runs, tmp_path):
    proc = _run(core_env, "-m", "swarm", "plot", str(core_runs["--in-process"]), cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert list((core_runs["--in-process"] / "figures").glob("*.png"))


def test_one_version_string(core_env, core_runs, tmp_path):
    """``swarm --version``, summary.json and pyproject.toml agree."""
    proc = _run(core_env, "-m", "swarm", "--version", cwd=tmp_path)
    assert proc.returncode == 0
    assert proc.stdout.strip() == f"{DISTRIBUTION} {PROJECT['version']}"
    summary = json.loads((core_runs["--processes"] / "summary.json").read_text())
    assert summary["version"] == PROJECT["version"] == version()


@pytest.mark.slow
def test_grids_run_on_the_core_in_the_local_pool(core_env, tmp_path):
    """``compare``, ``sweep`` and the quick paper experiment, with the local process pool."""
    grid = tmp_path / "grid.toml"
    grid.write_text('name = "g"\n[base]\nticks = 6\n[axes]\nsurface = ["elliptic", "wavy"]\n')
    for args in (("compare", "--estimators", "persist,edmd-b", "--ticks", "6"),
                 ("sweep", str(grid)),
                 ("experiment", "paper", "--quick")):
        out = tmp_path / args[0]
        proc = _run(core_env, "-m", "swarm", *args, "--workers", "2", "--out", str(out),
                    cwd=tmp_path)
        assert proc.returncode == 0, proc.stdout + proc.stderr
        assert "FAILED" not in proc.stderr
    assert (tmp_path / "experiment" / "report.md").is_file()


REFUSALS = {  # python -m ARGS ({tmp}: the test's folder), and the extra it needs
    "run-dem": ("dem", ("swarm", "run", "--surface", "dem:{hills}", "--ticks", "6",
                        "--out", "{tmp}/out")),
    "world-dem": ("dem", ("world", "--config", "{tmp}/dem.toml", "--out", "{tmp}/out")),
    "compare-dem": ("dem", ("swarm", "compare", "--surface", "dem:{hills}",
                            "--estimators", "persist", "--out", "{tmp}/out")),
    "terrain": ("dem", ("swarm", "experiment", "terrain", "--dem", "{hills}",
                        "--leader-start", "10,10,1,0", "--out", "{tmp}/out")),
    "dem-crop": ("dem", ("swarm", "dem-crop", "{hills}", "{tmp}/out.tif")),
    "dem-from-npz": ("dem", ("swarm", "dem-from-npz", "{tmp}/out.tif")),
    "run-live": ("live", ("swarm", "run", "--live", "--ticks", "6", "--out", "{tmp}/out")),
    "watch": ("live", ("swarm", "watch", "--connect", "tcp/127.0.0.1:9", "--run-id", "x")),
    "replay": ("live", ("swarm", "replay", "{tmp}/out")),
    "compare-scheduler": ("cluster", ("swarm", "compare", "--scheduler", "tcp://127.0.0.1:9",
                                      "--out", "{tmp}/out")),
    "sweep-scheduler": ("cluster", ("swarm", "sweep", "{tmp}/grid.toml", "--scheduler",
                                    "tcp://127.0.0.1:9", "--out", "{tmp}/out")),
    "deploy": ("deploy", ("swarm", "deploy", "--followers", "1", "--out", "{tmp}/out")),
}


FAST_REFUSALS = ("run-dem", "world-dem", "run-live", "compare-scheduler", "deploy")
"""One refusal per extra (and the world's path) in the fast tier; the others are slow."""


@pytest.mark.parametrize("name", [name if name in FAST_REFUSALS
                                  else pytest.param(name, marks=pytest.mark.slow)
                                  for name in REFUSALS])
def test_a_feature_without_its_extra_is_refused_in_one_line(core_env, tmp_path, name):
    """Exit 2 and the one line naming the extra, before anything is written (at most the
    empty output folder the command checks first)."""
    (tmp_path / "grid.toml").write_text("[base]\nticks = 6\n[axes]\nseed = [0, 1]\n")
    dump_config(RunConfig(run_id="dem", surface=f"dem:{HILLS}"), tmp_path / "dem.toml")
    extra, template = REFUSALS[name]
    args = [arg.format(tmp=tmp_path, hills=HILLS) for arg in template]
    proc = _run(core_env, "-m", *args, cwd=tmp_path)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert proc.stderr.splitlines() == [f"error: {missing_extra_message(extra)}"]
    out = tmp_path / "out"
    assert not out.exists() or not any(out.iterdir()), "written before the refusal"
    assert not (tmp_path / "out.tif").exists()


def test_console_scripts_are_declared_and_start():
    """[project.scripts] names the four commands; each one's function shows its help, in a
    process of its own (it ends the process, :func:`protocol.cli.exit_process`)."""
    assert PROJECT["scripts"] == SCRIPTS
    for name, target in SCRIPTS.items():
        module, function = target.split(":")
        script = (f"import sys; sys.argv = [{name!r}, '--help']; "
                  f"from {module} import {function}; {function}()")
        proc = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True,
                              text=True, timeout=TIMEOUT_S)
        assert proc.returncode == 0 and "usage:" in proc.stdout, (name, proc.stderr)


def test_a_command_ends_its_process_with_its_status_and_flushed_output():
    """exit_process: the status given, what was printed and logged is out, and nothing after
    it runs (no interpreter finalisation, where a Zenoh thread could abort the process)."""
    script = ("import logging, sys; from protocol.cli import exit_process; "
              "logging.basicConfig(stream=sys.stderr); print('result', end=''); "
              "logging.getLogger('x').warning('logged'); exit_process(3); print('not ended')")
    proc = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True,
                          text=True, timeout=TIMEOUT_S)
    assert (proc.returncode, proc.stdout) == (3, "result")
    assert "logged" in proc.stderr


def _installed_from_this_checkout() -> metadata.Distribution | None:
    """The installed distribution made from this checkout (pip records where it came from),
    if any; not an ``.egg-info`` that an install left in the checkout itself."""
    for dist in metadata.distributions(name=DISTRIBUTION):
        if json.loads(dist.read_text("direct_url.json") or "{}").get("url") == ROOT.as_uri():
            return dist
    return None


INSTALLED = _installed_from_this_checkout()


@pytest.mark.skipif(INSTALLED is None, reason=f"the installed {DISTRIBUTION} is not this "
                                              "checkout (.ci/run installs it editable)")
def test_the_installed_commands_and_metadata_are_this_checkouts(tmp_path):
    """Installed from this checkout (as .ci/run does): the metadata's version is the
    checkout's (reinstall after changing it), and each installed command runs."""
    dist = INSTALLED
    assert dist.version == PROJECT["version"] == version()
    assert {ep.name: ep.value for ep in dist.entry_points
            if ep.group == "console_scripts"} == SCRIPTS
    scripts = Path(sysconfig.get_path("scripts"))
    for name in SCRIPTS:
        proc = subprocess.run([str(scripts / name), "--help"], cwd=tmp_path,
                              capture_output=True, text=True, timeout=TIMEOUT_S)
        assert proc.returncode == 0 and "usage:" in proc.stdout, proc.stderr
    proc = subprocess.run([str(scripts / "swarm"), "--version"], capture_output=True, text=True,
                          timeout=TIMEOUT_S)
    assert proc.stdout.strip() == f"{DISTRIBUTION} {PROJECT['version']}"
