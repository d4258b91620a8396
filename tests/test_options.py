"""Each run option is declared once (protocol.config): the flags, ``--help``, the TOML keys,
the agents' settings, the refusal of options that do nothing and the options table of
docs/options.md all come from that declaration; and every command ends the same way (one
line, design §9's exit statuses)."""
from __future__ import annotations

import argparse
import dataclasses
import re
import signal
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from protocol.config import (
    DEFAULTS,
    OPTIONS,
    AgentBrief,
    AgentSettings,
    Option,
    RunConfig,
    config_from_dict,
    dump_config,
    flag_of,
    load_config,
    options_table,
)
from swarm.cli import CLI_DEFAULTS, build_parser, config_from_args, main
from swarm.grid import estimator_axis, expand

ROOT = Path(__file__).resolve().parents[1]
WORLD_ONLY = ("surface", "surface_params", "leader_start", "seed", "sensing_range",
              "pipelined", "ros2", "ros_domain")


def one_error_line(capsys) -> str:
    err = capsys.readouterr().err
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    return lines[0]


def other_value(declared: Option):
    """A valid value of ``declared`` other than its default."""
    if declared.kind is bool:
        return not declared.default
    if declared.choices:
        return next(c for c in declared.choices if c != declared.default and c not in "defg")
    if declared.kind is int:
        return declared.default + 1
    return declared.default / 2 if declared.default else 0.5


def flags_for(name: str, value) -> list[str]:
    """The command line that sets option ``name`` to ``value``."""
    declared = OPTIONS[name]
    if declared.kind is bool:
        assert value != declared.default  # a switch only sets the other value
        return [flag_of(declared)]
    return [flag_of(declared), declared.show(value).strip('"')]


# --- one declaration -----------------------------------------------------------------------------

def test_agent_settings_are_the_agent_visible_options_and_nothing_world_only():
    names = [f.name for f in dataclasses.fields(AgentSettings)]
    assert names == [n for n, d in OPTIONS.items() if d.agents]
    assert not set(WORLD_ONLY) & set(names)
    assert {"estimator", "spacing", "followers", "noise_range", "mode"} <= set(names)
    settings = AgentSettings.from_config(RunConfig(side="right", followers=2))
    assert settings.side_sign == -1 and settings.step_timeout == 40.0


def test_every_number_has_a_unit_and_every_estimator_option_is_declared():
    from protocol.config import ESTIMATOR_OPTIONS, ESTIMATORS

    for name, declared in OPTIONS.items():
        if declared.kind is float:
            assert declared.unit, name
        if declared.needs is not None:
            assert declared.needs[0] in OPTIONS, name
    for estimator, names in ESTIMATOR_OPTIONS.items():
        assert estimator in ESTIMATORS and set(names) <= set(OPTIONS), estimator


def test_run_help_shows_every_default_and_unit(capsys):
    with pytest.raises(SystemExit):
        main(["run", "--help"])
    text = " ".join(capsys.readouterr().out.split())  # argparse wraps lines
    checked = 0
    for declared in OPTIONS.values():
        flag = flag_of(declared)
        if flag is None or declared.kind is bool:
            continue
        shown = text[text.index(f" {flag} "):]
        shown = shown[:shown.index("]") + 1]  # up to the end of its "[default ...]"
        default = CLI_DEFAULTS.get(declared.name) or declared.show(declared.default)
        assert f"[default {default}" in shown, (flag, shown)
        unit = {"1": "dimensionless"}.get(declared.unit, declared.unit)
        if default == "1" and unit.isalpha():  # a counted unit, in the singular for one
            unit = unit.removesuffix("s")
        assert unit in shown, (flag, shown)
        checked += 1
    assert checked >= 30


def test_docs_options_table_is_generated_from_the_declarations():
    """docs/options.md holds options_table() verbatim between its markers."""
    text = (ROOT / "docs" / "options.md").read_text(encoding="utf-8")
    table = text.split("<!-- options table: start -->\n", 1)[1].split(
        "<!-- options table: end -->", 1)[0]
    assert table == options_table()
    assert table.count("\n") == len(OPTIONS) + 2


def test_config_toml_lists_every_option_and_loads_back(tmp_path):
    config = RunConfig(run_id="all", estimator="arx", arx_order=3, gps=True, noise_gps=0.2,
                       mode="realtime", time_scale=0.5, leader_start=(1.0, 2.0, 1.0, 0.0))
    dump_config(config, tmp_path / "config.toml")
    text = (tmp_path / "config.toml").read_text()
    # every option but the table and those left to the world (max_speed: None, drive only)
    assert all(re.search(rf"^{name} = ", text, re.M) for name, declared in OPTIONS.items()
               if name != "surface_params" and declared.default is not None
               or name == "leader_start")
    assert load_config(tmp_path / "config.toml") == config


# --- options that do nothing -----------------------------------------------------------------

IDLE_CASES = [(name, "persist", ()) for name, d in OPTIONS.items() if d.estimators] + [
    ("velocity", "edmd", ()), ("time_scale", "edmd", ()), ("noise_gps", "edmd", ()),
    ("pipelined", "edmd", ("--mode", "realtime")),
]


@pytest.mark.parametrize("name, estimator, extra", IDLE_CASES,
                         ids=[f"{n}-{e}" for n, e, _ in IDLE_CASES])
def test_an_option_that_does_nothing_is_refused(tmp_path, capsys, name, estimator, extra):
    value = other_value(OPTIONS[name])
    status = main(["run", "--estimator", estimator, *extra, *flags_for(name, value),
                   "--out", str(tmp_path / "r")])
    assert status == 2
    line = one_error_line(capsys)
    assert line.startswith(f"error: {name} = {OPTIONS[name].show(value)} does nothing with ")
    assert not (tmp_path / "r").exists()  # nothing ran


@pytest.mark.parametrize("name", [n for n, d in OPTIONS.items() if d.estimators])
def test_the_estimators_that_use_an_option_take_it(name):
    value = other_value(OPTIONS[name])
    for estimator in OPTIONS[name].estimators:
        extra = {"dictionary": "c"} if name == "velocity" else {}
        assert getattr(RunConfig(estimator=estimator, **extra, **{name: value}), name) == value
    # your own estimator may read any of them
    assert getattr(RunConfig(estimator="tests.example_estimator:MeanStep", **{name: value}),
                   name) == value


def test_a_default_value_is_never_refused():
    """Given explicitly or not, a default does nothing new: a written config.toml (every
    option) loads back whatever the estimator."""
    for estimator in ("persist", "cv", "gp", "auto"):
        assert config_from_dict({**DEFAULTS, "estimator": estimator}).estimator == estimator


def _parse(*flags: str) -> RunConfig:
    return config_from_args(build_parser().parse_args(["run", *flags]))


def test_edmd_letter_in_run_is_edmd_on_that_dictionary(capsys):
    config = _parse("--estimator", "edmd-c", "--velocity", "oracle")
    assert (config.estimator, config.dictionary, config.velocity) == ("edmd", "c", "oracle")
    config = _parse("--estimator", "edmd-e")
    assert (config.estimator, config.dictionary, config.gps) == ("edmd", "e", True)
    with pytest.raises(ValueError, match='estimator edmd-c means dictionary = "c", but '
                                         'dictionary = "b" is given'):
        _parse("--estimator", "edmd-c", "--dictionary", "b")
    assert main(["run", "--estimator", "edmd-z"]) == 2
    assert "estimator must be one of" in one_error_line(capsys)


ROUND_TRIPS = {
    "edmd-c": ["--estimator", "edmd-c", "--velocity", "estimated", "--noise-velocity", "0.02"],
    "arx": ["--estimator", "arx", "--arx-order", "2", "--noise-range", "0.01"],
    "gp": ["--estimator", "gp", "--gp-samples", "5", "--gps", "--noise-gps", "0.1"],
    "kalman": ["--estimator", "kalman", "--kalman-accel", "0.01", "--noise-bearing", "0.01",
               "--unpipelined"],
}


@pytest.mark.parametrize("flags", ROUND_TRIPS.values(), ids=ROUND_TRIPS)
def test_run_config_toml_repeats_the_run_exactly(tmp_path, flags):
    first, again = tmp_path / "first", tmp_path / "again"
    common = ["--surface", "wavy", "--ticks", "8", "--followers", "2", "--seed", "3",
              "--in-process"]
    assert main(["run", *common, *flags, "--out", str(first)]) == 0
    assert main(["run", "--config", str(first / "config.toml"), "--in-process",
                 "--out", str(again)]) == 0
    for name in ("config.toml", "ticks.csv", "observations.csv"):
        assert (again / name).read_bytes() == (first / name).read_bytes(), name


def test_compare_gives_each_estimator_the_options_it_uses(capsys):
    base = {"dictionary": "c", "velocity": "estimated", "gp_samples": 5}
    runs = expand("compare", base, [estimator_axis(["persist", "edmd-b", "edmd", "gp"])])
    got = {r.labels["estimator"]: (r.config.estimator, r.config.dictionary, r.config.velocity,
                                   r.config.gp_samples) for r in runs}
    assert got == {"persist": ("persist", "b", "lagged", 8),
                   "edmd-b": ("edmd", "b", "lagged", 8),
                   "edmd": ("edmd", "c", "estimated", 8),
                   "gp": ("gp", "b", "lagged", 5)}
    with pytest.raises(ValueError, match=r'^dictionary = "c" does nothing in any run with '
                                         r'estimator cv \(only edmd uses it\)'):
        expand("compare", {"dictionary": "c"}, [estimator_axis(["persist", "cv"])])
    with pytest.raises(ValueError, match="axis 'estimator' sets it in every run"):
        expand("compare", {"estimator": "gp"}, [estimator_axis(["persist", "cv"])])
    assert main(["compare", "--estimator", "gp", "--estimators", "persist,cv"]) == 2
    assert "compare takes --estimators" in one_error_line(capsys)
    assert main(["compare", "--dictionary", "c", "--estimators", "persist,cv"]) == 2
    assert "does nothing in any run" in one_error_line(capsys)


# --- one CLI behaviour ---------------------------------------------------------------------------

def test_the_session_mode_flag_has_one_name(capsys):
    from agents.cli import parser

    p = parser("test", "an agent")
    assert p.parse_args(["--config", "c.toml", "--session-mode", "peer"]).session_mode == "peer"
    with pytest.raises(SystemExit) as exit_:
        p.parse_args(["--config", "c.toml", "--mode", "peer"])
    assert exit_.value.code == 2
    with pytest.raises(SystemExit) as exit_:
        main(["watch", "--connect", "tcp/127.0.0.1:7447", "--run-id", "r", "--mode", "peer"])
    assert exit_.value.code == 2
    assert isinstance(build_parser(), argparse.ArgumentParser)


def test_plot_refuses_bad_input_and_overwriting(tmp_path, capsys):
    assert main(["plot", str(tmp_path)]) == 2
    assert "is not a results folder" in one_error_line(capsys)
    run = tmp_path / "run"
    assert main(["run", "--ticks", "6", "--in-process", "--plot", "--out", str(run)]) == 0
    capsys.readouterr()
    assert main(["plot", str(run)]) == 2
    assert "holds the run's figures already" in one_error_line(capsys)
    assert main(["plot", str(run), "--force"]) == 0


def test_dem_from_npz_refuses_bad_input_and_overwriting(tmp_path, capsys):
    pickled = tmp_path / "objects.npz"
    np.savez(pickled, elevation=np.array([object()], dtype=object))
    not_zip = tmp_path / "text.npz"
    not_zip.write_text("not an archive")
    for npz in (pickled, not_zip, tmp_path / "missing.npz"):
        assert main(["dem-from-npz", str(tmp_path / "o.tif"), "--npz", str(npz)]) == 2
        line = one_error_line(capsys)
        assert line.startswith(f"error: npz '{npz}': ") and "allow_pickle" not in line
    (tmp_path / "o.tif").write_text("keep me")
    assert main(["dem-from-npz", str(tmp_path / "o.tif")]) == 2
    assert "exists; choose another path or replace it (--force)" in one_error_line(capsys)
    assert (tmp_path / "o.tif").read_text() == "keep me"


def test_run_refuses_to_overwrite_results_without_force(tmp_path, capsys):
    out = tmp_path / "r"
    assert main(["run", "--ticks", "6", "--in-process", "--out", str(out)]) == 0
    before = (out / "ticks.csv").read_bytes()
    capsys.readouterr()
    assert main(["run", "--ticks", "7", "--in-process", "--out", str(out)]) == 2
    assert "already holds a run's results" in one_error_line(capsys)
    assert (out / "ticks.csv").read_bytes() == before
    assert main(["run", "--ticks", "7", "--in-process", "--out", str(out), "--force"]) == 0
    assert (out / "ticks.csv").read_bytes() != before


def test_a_folder_holding_results_is_refused_alike_by_world_and_swarm_run(tmp_path, capsys):
    """A folder with results but no summary (a world killed before writing one) is refused
    before anything ran, status 2, by ``python -m world`` and ``swarm run`` alike."""
    from protocol.session import free_tcp_endpoint

    out = tmp_path / "r"
    out.mkdir()
    (out / "ticks.csv").write_text("kept\n")
    dump_config(RunConfig(run_id="again", ticks=6), tmp_path / "c.toml")
    world = subprocess.run([sys.executable, "-m", "world", "--config", str(tmp_path / "c.toml"),
                            "--listen", free_tcp_endpoint(), "--out", str(out)],
                           cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert world.returncode == 2, world.stderr
    assert world.stderr.count("error:") == 1 and "already holds results" in world.stderr
    assert main(["run", "--ticks", "6", "--in-process", "--out", str(out)]) == 2
    assert "already holds results" in one_error_line(capsys)
    assert (out / "ticks.csv").read_text() == "kept\n"


@pytest.mark.parametrize("signum, status", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
@pytest.mark.parametrize("command", [("agents.leader",), ("world", "--out", "run")],
                         ids=["agent", "world"])
def test_stopping_a_process_that_waits_for_its_router_is_prompt_and_quiet(tmp_path, signum,
                                                                          status, command):
    """A session still connecting (no Zenoh router answers) waits inside Zenoh; Ctrl-C or
    SIGTERM there ends the process at once with its status and no traceback (`watch`, the
    agents and a world given only ``--connect`` open their session the same way). The
    endpoint is a plain socket of the test's, so the process's first connection attempt shows
    it is inside that wait."""
    from tests.waiting import signalled

    config = RunConfig(run_id="stop", start_timeout=60.0)
    dump_config(config, tmp_path / "c.toml")
    AgentBrief.of(config, 0).write(tmp_path / "leader.toml")
    module, *extra = command
    extra = [str(tmp_path / x) if x == "run" else x for x in extra]
    with socket.socket() as fake_router:
        fake_router.bind(("127.0.0.1", 0))
        fake_router.listen()
        fake_router.settimeout(30.0)
        endpoint = f"tcp/127.0.0.1:{fake_router.getsockname()[1]}"
        given = "c.toml" if module == "world" else "leader.toml"
        proc = subprocess.Popen([sys.executable, "-m", module, "--config",
                                 str(tmp_path / given), "--connect", endpoint, *extra],
                                cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                text=True)
        try:
            connection, _ = fake_router.accept()
            connection.close()
        finally:
            code, _, err = signalled(proc, signum, timeout=10.0)
    assert code == status
    assert err.strip() == "interrupted", err
