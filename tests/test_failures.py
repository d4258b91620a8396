"""Clear failures: every refusal of a command is one line on stderr (never a traceback, never a
Zenoh source path), every number of a run is range-checked, and a run that estimated nothing
is not reported as a plain success."""
from __future__ import annotations

import errno
import json
import math
import os
import threading

import pytest
import zenoh

import swarm.cli
import world.checkpoint
import world.main
import world.results
from agents import leader
from agents.follower import run_follower
from agents.leader import run_leader
from agents.link import AgentAbort
from protocol.cli import add_log_level_flag
from protocol.config import (
    MAX_CONFIG_BYTES,
    OPTIONS,
    AgentBrief,
    RunConfig,
    dump_config,
    load_config,
)
from protocol.session import free_tcp_endpoint, zenoh_config
from swarm.cli import empty_followers


def one_error_line(capsys) -> str:
    """stderr must be exactly one line starting with ``error:``; return it."""
    err = capsys.readouterr().err
    lines = err.strip("\n").split("\n")
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert "Traceback" not in err and ".rs:" not in err, err
    return lines[0]


# --- configuration ranges ----------------------------------------------------------------------


def _beyond(low, high, low_open):
    """Values just outside a range (NaN as well for floats)."""
    out = [high * 10 if high > 0 else high + 1] if math.isfinite(high) else []
    out.append(low - 1 if not low_open else low)
    return out


@pytest.mark.parametrize("name, value", [
    (name, value) for name, declared in OPTIONS.items()
    if declared.kind is int and declared.low is not None
    for value in (declared.low - 1, declared.high + 1)
] + [
    (name, value) for name, declared in OPTIONS.items()
    if declared.kind is float and declared.low is not None
    for value in [*_beyond(declared.low, declared.high, declared.low_open), math.nan]
])
def test_every_numeric_option_is_range_checked(name, value):
    with pytest.raises(ValueError, match=rf"^{name} must be (an integer )?in [\[(]"):
        RunConfig(**{name: value})


def test_absurd_timeout_named_with_the_file(tmp_path):
    path = tmp_path / "run.toml"
    path.write_text("agent_timeout = 1e10\n")
    with pytest.raises(ValueError) as err:
        load_config(path)
    assert str(err.value) == (f"config file {path}: "
                              "agent_timeout must be in (0, 3600], got 10000000000.0")


@pytest.mark.parametrize("text, fragment", [
    ("a = " + "[" * 5000 + "]" * 5000, "nests tables or arrays too deeply"),
    ("surface_params = {a = {b = {c = 1.0}}}", "nests tables or arrays deeper than 3 levels"),
    ("# " + "x" * MAX_CONFIG_BYTES, "is larger than 64 KiB"),
    ("followers = 1" + "0" * 5000, "is not valid TOML: Exceeds the limit"),
    ("followers = [", "is not valid TOML"),
    ("surface_params = {\"a b\" = 1.0}", "surface_params names must be identifiers"),
    ("surface_params = {" + ", ".join(f"p{i} = 1.0" for i in range(40)) + "}",
     "surface_params must be a table of at most 32 numbers"),
    ("leader_start = 5", "leader_start must be X,Y,VX,VY, got 5"),
    ("surface = \"" + "s" * 5000 + "\"", "surface must be a preset name"),
], ids=["deep-array", "deep-table", "huge-file", "huge-int", "syntax", "param-name",
        "many-params", "leader-start", "long-surface"])
def test_bad_toml_is_one_line_naming_the_file(tmp_path, text, fragment):
    path = tmp_path / "run.toml"
    path.write_text(text)
    with pytest.raises(ValueError) as err:
        load_config(path)
    message = str(err.value)
    assert message.startswith(f"config file {path}") and fragment in message
    assert "\n" not in message and len(message) < 400


def test_unreadable_config_files(tmp_path):
    (tmp_path / "latin1.toml").write_bytes(b"surface = \"\xe9\"\n")
    with pytest.raises(ValueError, match="is not UTF-8 text"):
        load_config(tmp_path / "latin1.toml")
    with pytest.raises(ValueError, match="cannot read config file .*Is a directory"):
        load_config(tmp_path)


def test_log_level_flag():
    import argparse

    p = argparse.ArgumentParser()
    add_log_level_flag(p)
    assert p.parse_args(["--log-level", "debug"]).log_level == "DEBUG"
    assert p.parse_args([]).log_level == "WARNING"
    with pytest.raises(SystemExit):
        p.parse_args(["--log-level", "LOUD"])


# --- the world's command line -----------------------------------------------------------------


@pytest.fixture
def run_toml(tmp_path):
    path = tmp_path / "run.toml"
    dump_config(RunConfig(run_id="fail", ticks=6, start_timeout=5.0), path)
    return path


def _world(run_toml, *extra) -> int:
    return world.main.main(["--config", str(run_toml), "--listen", free_tcp_endpoint(), *extra])


def test_world_refuses_a_bad_log_level(run_toml, capsys):
    with pytest.raises(SystemExit) as exc:
        _world(run_toml, "--log-level", "LOUD")
    assert exc.value.code == 2
    assert "argument --log-level: invalid choice: 'LOUD'" in capsys.readouterr().err


@pytest.mark.parametrize("out, fragment", [
    ("FILE", "is a file, not a folder"),
    ("/proc/x", "--out /proc/x cannot hold results: No such file or directory"),
    ("/proc/self/status/x", "cannot hold results: Not a directory"),
], ids=["file", "proc", "under-a-file"])
def test_world_refuses_an_unusable_out(run_toml, tmp_path, capsys, out, fragment):
    if out == "FILE":
        out = str(tmp_path / "a-file")
        (tmp_path / "a-file").write_text("not a folder")
    assert _world(run_toml, "--out", out) == 2  # refused before anything ran, as swarm run
    assert fragment in one_error_line(capsys)


def test_world_on_a_busy_port_is_one_line(run_toml, tmp_path, capsys):
    import socket

    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        endpoint = f"tcp/127.0.0.1:{held.getsockname()[1]}"
        status = world.main.main(["--config", str(run_toml), "--listen", endpoint,
                                  "--out", str(tmp_path / "out")])
    assert status == 1
    assert one_error_line(capsys).startswith(
        f"error: Zenoh: Can not create a new TCP listener bound to {endpoint}")


BAD_SURFACE_MODULES = {
    "syntax": ("def surface(:\n", "SyntaxError: "),
    "raises": ("raise RuntimeError('no terrain today')\n", "RuntimeError: no terrain today"),
    "factory": ("def surface():\n    return 1 / 0\n", "failed to build: ZeroDivisionError"),
}


def _broken_surface_module(tmp_path, monkeypatch, module: str, kind: str) -> str:
    """Write the broken module ``kind`` as ``module`` on the import path; its error fragment."""
    source, fragment = BAD_SURFACE_MODULES[kind]
    (tmp_path / f"{module}.py").write_text(source)
    monkeypatch.syspath_prepend(str(tmp_path))
    return fragment


@pytest.mark.parametrize("kind", BAD_SURFACE_MODULES)
def test_world_reports_a_broken_surface_module(tmp_path, monkeypatch, capsys, kind):
    module = f"broken_surface_{kind}"
    fragment = _broken_surface_module(tmp_path, monkeypatch, module, kind)
    path = tmp_path / "run.toml"
    dump_config(RunConfig(run_id="fail", surface=f"{module}:surface"), path)
    assert _world(path, "--out", str(tmp_path / "out")) == 2  # refused before anything ran
    assert not (tmp_path / "out").exists()
    line = one_error_line(capsys)
    assert f"surface '{module}:surface'" in line and fragment in line


def _failing_writes(monkeypatch, code: int, after: int) -> None:
    """Results writes succeed ``after`` times, then fail as a full or read-only disk would."""
    real, calls = world.results.write_atomic, []

    def write_atomic(path, text):
        calls.append(path)
        if len(calls) > after:
            raise OSError(code, os.strerror(code), str(path))
        real(path, text)

    monkeypatch.setattr(world.results, "write_atomic", write_atomic)


class _Agents:
    """The leader and followers as threads with their own sessions. Once the world has gone,
    :meth:`stop` closes their sessions, as ``swarm run`` does, instead of letting them wait
    out their start timeout for it to come back."""

    def __init__(self, config: RunConfig, endpoint: str):
        from protocol.config import AgentSettings

        settings = AgentSettings.from_config(config)
        bodies = [lambda s: run_leader(s, settings)]
        bodies += [lambda s, k=k: run_follower(s, settings, k)
                   for k in range(1, config.followers + 1)]
        self._lock = threading.Lock()
        self._sessions: list[zenoh.Session] = []
        self._stopped = False
        self.threads = [threading.Thread(target=self._agent, args=(b, endpoint), daemon=True)
                        for b in bodies]
        for t in self.threads:
            t.start()

    def _agent(self, body, endpoint: str) -> None:
        try:
            with zenoh.open(zenoh_config("peer", connect=[endpoint])) as session:
                with self._lock:
                    self._sessions.append(session)
                    if self._stopped:
                        return
                body(session)
        except AgentAbort:  # the world went away, or stop() closed the session
            return
        except (zenoh.ZError, RuntimeError):  # closing a session stop() closed already
            if not self._stopped:
                raise

    def stop(self, timeout: float) -> None:
        with self._lock:
            self._stopped = True
            for session in self._sessions:
                session.close()
        for t in self.threads:
            t.join(timeout=timeout)


def _world_with_agents(config: RunConfig, path, out) -> int:
    """Run ``python -m world`` on the config file ``path`` in a thread, with the leader and
    followers as threads, into ``out``; its exit status once everyone has ended."""
    endpoint = free_tcp_endpoint()
    result: list[int] = []
    world_thread = threading.Thread(target=lambda: result.append(world.main.main(
        ["--config", str(path), "--listen", endpoint, "--out", str(out)])))
    world_thread.start()
    agents = _Agents(config, endpoint)
    world_thread.join(timeout=60)
    agents.stop(timeout=30)
    assert not world_thread.is_alive() and not any(t.is_alive() for t in agents.threads)
    assert len(result) == 1
    return result[0]


@pytest.mark.parametrize("code", [errno.ENOSPC, pytest.param(errno.EROFS, marks=pytest.mark.slow)])
def test_world_reports_a_failing_results_disk(tmp_path, monkeypatch, capsys, code):
    config = RunConfig(run_id="disk", ticks=8, start_timeout=10.0)
    path = tmp_path / "run.toml"
    dump_config(config, path)
    _failing_writes(monkeypatch, code, after=3)
    assert _world_with_agents(config, path, tmp_path / "out") == 1
    line = one_error_line(capsys)
    assert line.startswith(f"error: cannot write the results in {tmp_path / 'out'}: "
                           f"{os.strerror(code)}: ")


def test_a_failing_journal_write_is_reported_as_a_failing_results_disk(tmp_path, monkeypatch,
                                                                      capsys):
    """The request journal is a results file too: when its append fails (the disk filled while
    a request was answered), the world ends with the same one line as for any results file,
    naming it, and the summary says why — not a different message for the file that filled
    first."""
    config = RunConfig(run_id="journal", ticks=8, start_timeout=10.0)
    path = tmp_path / "run.toml"
    dump_config(config, path)
    real, calls = world.checkpoint.Journal.add, []

    def add(self, *args):
        calls.append(args)
        if len(calls) > 10:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(self.path))
        real(self, *args)

    monkeypatch.setattr(world.checkpoint.Journal, "add", add)
    out = tmp_path / "out"
    assert _world_with_agents(config, path, out) == 1
    assert one_error_line(capsys) == (f"error: cannot write the results in {out}: "
                                      f"No space left on device: {out}/world_requests.jsonl")
    summary = json.loads((out / "summary.json").read_text())
    assert not summary["complete"]
    assert summary["reason"] == "cannot write world_requests.jsonl: No space left on device"


# --- agents -------------------------------------------------------------------------------------


def test_agent_without_a_world_says_so_in_one_line(tmp_path, capsys):
    path = AgentBrief.of(RunConfig(run_id="alone", start_timeout=1.0), 0).write(
        tmp_path / "leader.toml")
    endpoint = free_tcp_endpoint()
    assert leader.main(["--config", str(path), "--connect", endpoint]) == 1
    line = one_error_line(capsys)
    assert line.startswith(f"error: no world reachable at {endpoint} within 1 s")


def test_agent_refuses_a_bad_log_level(run_toml, capsys):
    with pytest.raises(SystemExit) as exc:
        leader.main(["--config", str(run_toml), "--connect", free_tcp_endpoint(),
                     "--log-level", "LOUD"])
    assert exc.value.code == 2 and "invalid choice: 'LOUD'" in capsys.readouterr().err


# --- swarm run ----------------------------------------------------------------------------------


def _swarm(*args: str) -> int:
    return swarm.cli.main(["run", "--in-process", *args])


@pytest.mark.parametrize("args, status, fragment", [
    (["--out", "/proc/x"], 2, "--out /proc/x cannot hold results"),
    (["--agent-timeout", "1e10"], 2, "agent_timeout must be in (0, 3600], got 10000000000.0"),
    (["--followers", "0"], 2, "followers must be an integer in [1, 1000], got 0"),
    (["--ticks", "3"], 2, "init_ticks (4) must be at most ticks (3): raise ticks or lower"),
    (["--init-ticks", "1"], 2, "init_ticks must be an integer in [2, 1000000], got 1"),
    (["--surface", "no_such_module_here:surface"], 2, "cannot import module 'no_such_module_here'"),
], ids=["out-proc", "timeout", "followers", "few-ticks", "init-ticks", "no-module"])
def test_swarm_run_refusals_are_one_line(tmp_path, monkeypatch, capsys, args, status, fragment):
    monkeypatch.chdir(tmp_path)
    assert _swarm(*args) == status
    assert fragment in one_error_line(capsys)


def test_swarm_run_refuses_a_file_as_out_and_a_bad_log_level(tmp_path, capsys):
    (tmp_path / "f").write_text("x")
    assert _swarm("--out", str(tmp_path / "f")) == 2
    assert "is a file, not a folder" in one_error_line(capsys)
    with pytest.raises(SystemExit):
        _swarm("--log-level", "LOUD", "--out", str(tmp_path / "r"))
    assert "invalid choice: 'LOUD'" in capsys.readouterr().err


@pytest.mark.parametrize("command", [
    ["compare", "--estimators", "persist", "--ticks", "6"],
    ["experiment", "paper", "--quick"],
    ["experiment", "terrain", "--dem", "unused.tif", "--leader-start", "0,0,1,0"],
], ids=["compare", "paper", "terrain"])
@pytest.mark.parametrize("out", ["/proc/x", "FILE"])
def test_grid_commands_refuse_an_unusable_out_before_running(tmp_path, monkeypatch, capsys,
                                                             command, out):
    """One line and status 2 before any run: nothing is left half-written."""
    monkeypatch.chdir(tmp_path)
    if out == "FILE":
        out = str(tmp_path / "a-file")
        (tmp_path / "a-file").write_text("not a folder")
    assert swarm.cli.main([*command, "--out", out]) == 2
    assert ("cannot hold results" if out == "/proc/x" else "is a file, not a folder") in (
        one_error_line(capsys))
    assert not (tmp_path / "runs").exists()


@pytest.mark.parametrize("kind", BAD_SURFACE_MODULES)
def test_swarm_run_reports_a_broken_surface_module(tmp_path, monkeypatch, capsys, kind):
    module = f"broken_swarm_surface_{kind}"
    fragment = _broken_surface_module(tmp_path, monkeypatch, module, kind)
    assert _swarm("--surface", f"{module}:surface", "--out", str(tmp_path / "out")) == 2
    assert fragment in one_error_line(capsys)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("code", [errno.ENOSPC, pytest.param(errno.EROFS, marks=pytest.mark.slow)])
def test_swarm_run_reports_a_failing_results_disk(tmp_path, monkeypatch, capsys, code):
    _failing_writes(monkeypatch, code, after=3)
    out = tmp_path / "out"
    assert _swarm("--ticks", "8", "--out", str(out)) == 1
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("error")]
    assert lines == [f"error: cannot write the results in {out}: "
                     f"{os.strerror(code)}: {lines[0].rsplit(': ', 1)[-1]}"]
    assert "Traceback" not in err


def test_swarm_run_with_nothing_estimated_is_not_a_plain_success(tmp_path, capsys):
    """A run in which a follower estimated nothing did not do what was asked: status 1
    (design §9 has no other), with the warning that says why."""
    assert _swarm("--ticks", "4", "--init-ticks", "4", "--out", str(tmp_path / "r")) == 1
    err = capsys.readouterr().err
    assert "warning: follower 1 estimated no tick: estimation starts at tick 4 and the run has " \
           "4 ticks (0 missed)" in err
    assert _swarm("--ticks", "8", "--delays", "1000", "--out", str(tmp_path / "d")) == 1
    assert "warning: follower 1 estimated no tick: its estimator was never ready, persist " \
           "stood in on all 4 ticks from tick 4" in capsys.readouterr().err


def test_empty_followers_names_each_case():
    """The rule behind exit 3 (a live realtime run that misses every tick depends on timing,
    so the missed-every-tick case is checked on summaries)."""
    def follower(estimated, missed, fallback=0):
        return {"estimated_ticks": estimated, "missed_ticks": missed, "fallback_ticks": fallback}

    summary = {"ticks_completed": 40, "followers": {
        "1": follower(36, 0), "2": follower(30, 40), "3": follower(0, 3),
        "4": follower(0, 0, fallback=36)}}
    assert empty_followers(summary, init_ticks=4) == [
        "follower 2 missed every tick (40 of 40): it never settled in time, its numbers "
        "measure nothing it did",
        "follower 3 estimated no tick: estimation starts at tick 4 and the run has 40 ticks "
        "(3 missed)",
        "follower 4 estimated no tick: its estimator was never ready, persist stood in on all "
        "36 ticks from tick 4 (does it need more samples than the run has?)",
    ]
    summary["followers"] = {"1": follower(36, 0)}
    assert empty_followers(summary, init_ticks=4) == []
