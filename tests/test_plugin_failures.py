"""A plug-in estimator that fails (design §6): a factory that raises, or a method that raises
mid-run, ends the run with one line naming the estimator, the tick and the error, in every
layout and mode; no traceback, no wait for a timeout, no misleading warning after it."""
from __future__ import annotations

import pytest

import swarm.cli
from agents.policies import NotReady, load_estimator
from agents.policies.plugin import EstimatorFailed
from protocol.config import AgentSettings, RunConfig
from protocol.messages import Sensing

FAILS = "tests.example_estimator:FailsAtTick"


def _stderr_lines(capsys) -> list[str]:
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    return [line for line in err.splitlines() if line]


FAILING = {
    "factory": ("json:loads", "estimator 'json:loads': its factory loads raised TypeError: the "
                              "JSON object must be str, bytes or bytearray, not AgentSettings"),
    "method": (FAILS, f"estimator '{FAILS}': propose raised at tick 5: KeyError: "
                      "\"no such column 'x'\""),
}
FAST = {("factory", "--in-process", "lockstep"), ("method", "--processes", "realtime")}
"""The fast tier's cases: each failure, layout and mode once; the other six are slow."""


def _cases():
    for kind, (estimator, said) in FAILING.items():
        for layout in ("--in-process", "--processes"):
            for mode in ("lockstep", "realtime"):
                yield pytest.param(layout, mode, estimator, said, id=f"{kind}-{layout}-{mode}",
                                   marks=() if (kind, layout, mode) in FAST else pytest.mark.slow)


@pytest.mark.parametrize("layout, mode, estimator, said", list(_cases()))
def test_a_failing_plugin_ends_the_run_in_one_line(tmp_path, capsys, layout, mode, estimator,
                                                   said):
    pace = ["--time-scale", "0.2"] if mode == "realtime" else []
    status = swarm.cli.main(["run", layout, "--mode", mode, *pace,
                             "--estimator", estimator, "--ticks", "40",
                             "--out", str(tmp_path / "out")])
    assert status == 1
    lines = _stderr_lines(capsys)
    assert len(lines) == 1 and lines[0].startswith("error: "), lines
    assert said in lines[0], lines[0]
    if layout == "--processes":  # the agent's own line, and where its log is
        assert str(tmp_path / "out" / "logs" / "agent-1.log") in lines[0]


def test_a_plugin_method_error_names_the_tick_and_not_ready_passes():
    policy = load_estimator(FAILS, AgentSettings.from_config(RunConfig()))
    with pytest.raises(NotReady):  # not a failure: the follower falls back to persist
        policy.propose(Sensing(tick=0, r=1.0, theta=0.0))
    for tick in range(5):
        policy.record(Sensing(tick=tick, r=1.0 + tick, theta=0.0, rod=(1.0, 0.0)), None)
    with pytest.raises(EstimatorFailed, match="propose raised at tick 5: KeyError"):
        policy.propose(Sensing(tick=5, r=6.0, theta=0.0))
