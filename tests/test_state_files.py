"""State files are data (design §4): the follower's replay log and the world's checkpoint refuse
anything corrupt, truncated, foreign or crafted with one line naming the file and why, and a
planted pickle never runs."""
from __future__ import annotations

import json
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from agents.checkpoint import Entry, StateLog, StateLogError, replay, state_path
from agents.policies import make_policy
from protocol.config import AgentSettings, RunConfig, dump_config
from protocol.messages import Drive, Move, Sensing, Snap
from protocol.record import RESULT_FILES
from protocol.session import free_tcp_endpoint
from swarm.launch import write_briefs
from world import checkpoint as world_checkpoint

ROOT = Path(__file__).resolve().parents[1]
RUN, START = "state-run", "0123456789abcdef"


def _entries(n: int = 5) -> list[Entry]:
    out = []
    for j in range(n):
        settled = Sensing(tick=j, r=3.5 + 0.01 * j, theta=0.1 * j, rod=None,
                          velocity=None if j == 0 else (0.5, -0.25))
        out.append(Entry(tick=j, skips=0, settled=settled,
                         target=None if j % 2 else (0.125 * j, -1.0 / 3.0)))
    return out


def _log(tmp_path: Path, entries: list[Entry]) -> Path:
    state, existing = StateLog.open(tmp_path, RUN, 1, START)
    assert existing == []
    for entry in entries:
        state.append(entry)
    return state.path


def test_replay_log_round_trips_exactly_and_rebuilds_the_policy(tmp_path):
    entries = _entries()
    _log(tmp_path, entries)
    _, read = StateLog.open(tmp_path, RUN, 1, START)
    assert read == entries  # floats through JSON exactly
    settings = AgentSettings.from_config(RunConfig(estimator="auto"))
    live, rebuilt = make_policy(settings), make_policy(settings)
    for e in entries:
        live.record(e.settled, None if e.target is None else np.asarray(e.target))
    replay(rebuilt, read)
    pre = Sensing(tick=5, r=3.6, theta=0.45, rod=(0.1, 0.2), velocity=(0.5, -0.25))
    assert rebuilt.propose(pre).offset.tolist() == live.propose(pre).offset.tolist()


class _Calls:
    """A policy that notes what replay asks of it."""

    def __init__(self) -> None:
        self.calls: list[str] = []

    def skip(self) -> None:
        self.calls.append("skip")

    def learn(self, settled, target, before=None):
        self.calls.append(f"learn {settled.tick}")


def test_replay_bridges_every_tick_that_passed_without_a_settle():
    """Ticks 2-3 passed unseen (``skips``) and tick 5 was missed (no settle): each is one
    ``skip``, so a policy learns the ticks it saw at their true spacing, as the live loop
    (``run_follower``: ``policy.skip()`` on a missed tick) did."""
    entries = _entries(2) + [Entry(tick=4, skips=2, settled=_entries(5)[4].settled,
                                   target=None),
                             Entry(tick=5, skips=0, settled=None, target=None),
                             Entry(tick=6, skips=0, settled=_entries(7)[6].settled,
                                   target=(0.5, 0.5))]
    policy = _Calls()
    replay(policy, entries)
    assert policy.calls == ["learn 0", "learn 1", "skip", "skip", "learn 4", "skip", "learn 6"]


def test_a_torn_last_line_is_a_tick_never_reported(tmp_path):
    path = _log(tmp_path, _entries())
    raw = path.read_bytes()
    path.write_bytes(raw[:-40])  # killed in the middle of appending the last tick
    _, read = StateLog.open(tmp_path, RUN, 1, START)
    assert [e.tick for e in read] == [0, 1, 2, 3]


def _refusal(tmp_path: Path, start: str = START, run: str = RUN, agent: int = 1) -> str:
    with pytest.raises(StateLogError) as err:
        StateLog.open(tmp_path, run, agent, start)
    message = str(err.value)
    assert "\n" not in message and str(state_path(tmp_path, agent)) in message
    return message


def test_corrupt_edited_and_truncated_files_are_refused(tmp_path):
    path = _log(tmp_path, _entries())
    lines = path.read_text().splitlines(keepends=True)
    path.write_text("".join(lines[:2] + [lines[2].replace("3.5", "9.5")] + lines[3:]))
    assert "fails its checksum" in _refusal(tmp_path)
    path.write_text("".join(lines[:2] + lines[3:]))  # a whole line gone from the middle
    assert "a line is missing or out of place" in _refusal(tmp_path)
    path.write_text("")
    assert "empty" in _refusal(tmp_path)
    path.write_bytes(b"\xff\xfe garbage\n")
    assert "not JSON" in _refusal(tmp_path)


def test_foreign_files_are_refused(tmp_path):
    _log(tmp_path, _entries())
    assert "another run, start or agent" in _refusal(tmp_path, start="feedfacefeedface")
    assert "another run, start or agent" in _refusal(tmp_path, run="other-run")
    state_path(tmp_path, 1).rename(state_path(tmp_path, 2))
    assert "another run, start or agent" in _refusal(tmp_path, agent=2)


def test_crafted_lines_with_valid_checksums_are_refused(tmp_path):
    from protocol.config import checked_line as _line

    header = {"schema": 1, "run_id": RUN, "agent": 1, "start": START}
    crafted = [
        {"tick": 0, "skips": 0, "settled": {"v": 1, "type": "sensing", "tick": 0, "r": "x"},
         "target": None},
        {"tick": 0, "skips": -5, "settled": None, "target": None},
        {"tick": 0, "skips": 0, "settled": None, "target": [1.0, 2.0]},
        {"tick": 0, "skips": 0, "settled": None, "target": None, "code": "__import__('os')"},
        {"tick": 1e9, "skips": 0, "settled": None, "target": None},
    ]
    for body in crafted:
        state_path(tmp_path, 1).write_text(_line(header) + _line(body))
        _refusal(tmp_path)


def test_a_planted_pickle_is_refused_and_never_runs(tmp_path):
    """The attack of the issue: a pickle planted where a follower keeps its state. The follower
    exits with one line naming the file; the pickle's payload never ran."""
    marker = tmp_path / "pwned"

    class Payload:
        def __reduce__(self):
            return (open, (str(marker), "w"))

    folder = tmp_path / "run"
    folder.mkdir()
    config = RunConfig(run_id="planted", followers=1, ticks=8, start_timeout=20.0)
    dump_config(config, folder / "config.toml")
    (folder / "state").mkdir()
    state_path(folder / "state", 1).write_bytes(pickle.dumps(Payload()))
    endpoint = free_tcp_endpoint()
    world = subprocess.Popen([sys.executable, "-m", "world",
                              "--config", str(folder / "config.toml"), "--listen", endpoint,
                              "--out", str(folder / "out")], cwd=ROOT,
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        follower = subprocess.run(
            [sys.executable, "-m", "agents.follower", "--id", "1", "--config",
             str(write_briefs(config, folder) / "follower-1.toml"), "--connect", endpoint],
            cwd=ROOT, capture_output=True, text=True, timeout=60)
    finally:
        world.kill()
        world.communicate(timeout=10)
    assert follower.returncode != 0
    errors = [line for line in follower.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "state file" in errors[0] and "refusing it" in errors[0], \
        follower.stderr
    assert "Traceback" not in follower.stderr
    assert not marker.exists()


def test_world_checkpoint_refuses_corrupt_foreign_and_edited_files(tmp_path):
    world_checkpoint.save(tmp_path, run_id="r1", start="ab", sim={"tick": 3},
                          offsets={"ticks.csv": 10, "observations.csv": 10}, wall_time=1.0)
    assert world_checkpoint.load(tmp_path, "r1")["sim"] == {"tick": 3}
    with pytest.raises(world_checkpoint.StateError, match="belongs to run 'r1'"):
        world_checkpoint.load(tmp_path, "r2")
    path = tmp_path / world_checkpoint.STATE_FILE
    body = json.loads(path.read_text())
    body["sim"]["tick"] = 30
    path.write_text(json.dumps(body))
    with pytest.raises(world_checkpoint.StateError, match="fails its checksum"):
        world_checkpoint.load(tmp_path, "r1")
    path.write_bytes(pickle.dumps({"tick": 3}))
    with pytest.raises(world_checkpoint.StateError, match="unreadable"):
        world_checkpoint.load(tmp_path, "r1")


def test_a_fresh_world_refuses_a_folder_with_results_unless_forced(tmp_path):
    for name in RESULT_FILES:
        (tmp_path / name).write_text("kept\n")
    (tmp_path / "summary.json").write_text(json.dumps({"run_id": "old-run"}))
    with pytest.raises(world_checkpoint.StateError, match="results of run 'old-run'"):
        world_checkpoint.claim(tmp_path)
    assert (tmp_path / "ticks.csv").read_text() == "kept\n"
    world_checkpoint.claim(tmp_path, force=True)
    assert not any((tmp_path / name).exists() for name in RESULT_FILES)


def test_the_last_log_removed_takes_its_emptied_folder_along(tmp_path):
    """Followers share a state folder: a complete run's logs go one by one, and the folder with
    the last (a folder holding anything else stays)."""
    folder = tmp_path / "state"
    logs = [StateLog.open(folder, RUN, agent, START)[0] for agent in (1, 2)]
    logs[0].remove()
    assert sorted(p.name for p in folder.iterdir()) == [state_path(folder, 2).name]
    logs[1].remove()
    assert not folder.exists()
    kept = StateLog.open(folder, RUN, 1, START)[0]
    (folder / "notes.txt").write_text("mine\n")
    kept.remove()
    assert [p.name for p in folder.iterdir()] == ["notes.txt"]


def test_the_request_journal_reads_back_what_the_world_answered_after_its_checkpoint(tmp_path):
    """The world's request journal (``world_requests.jsonl``): a resumed world gets back every
    request of the ticks after its checkpoint, equal to what it answered (actions through the
    protocol codec); the file stays bounded as ticks are checkpointed; a torn last line (never
    answered) is dropped; another start's file is refused in one line."""
    journal = world_checkpoint.Journal(tmp_path, RUN, START)
    journal.open()
    ticks = 3 * world_checkpoint.TRIM_LINES // 4
    for tick in range(ticks):
        journal.add(0, tick, 0, Drive(tick=tick, t=1.28 * tick))
        journal.add(1, tick, 0, ("sense", tick % 2 == 0))
        journal.add(1, tick, 1, Move(tick=tick, offset=(0.25, -1.0 / 3.0)))
        journal.add(1, tick, 2, Snap(tick=tick))
        journal.keep_after(tick - 1)  # each tick checkpointed once the next one began
    path = tmp_path / world_checkpoint.JOURNAL_FILE
    assert path.read_bytes().count(b"\n") <= 1 + world_checkpoint.TRIM_LINES + 8
    last = ticks - 1
    expected = [(0, last, 0, Drive(tick=last, t=1.28 * last)),
                (1, last, 0, ("sense", last % 2 == 0)),
                (1, last, 1, Move(tick=last, offset=(0.25, -1.0 / 3.0))),
                (1, last, 2, Snap(tick=last))]
    assert journal.read(2, last - 1) == expected
    from protocol.config import canonical_json  # a line is composed, not encoded: the same text
    assert all(world_checkpoint._entry_json(*e) == canonical_json(
        {"agent": e[0], "tick": e[1], "index": e[2],
         "request": world_checkpoint._request_body(e[3])})
        for e in [*expected, (1, last, 3, ("sense", True))])
    assert world_checkpoint.attempts(expected)[(1, last)] == [e[3] for e in expected[1:]]
    journal.close()
    with open(path, "ab") as torn:
        torn.write(b'{"agent": 1, "tick": ')
    assert world_checkpoint.Journal(tmp_path, RUN, START).read(2, last - 1) == expected
    with pytest.raises(world_checkpoint.StateError, match="header is not this run's"):
        world_checkpoint.Journal(tmp_path, RUN, "feedfacefeedface").read(2, last - 1)


def test_a_state_line_is_encoded_once_and_reads_back_whatever_its_layout():
    from protocol.config import checked_json, checked_line, checked_lines, checked_text
    body = {"b": [1.5, None, 'q"uote'], "a": {"z": 1e-300, "y": -0.0}}
    text = checked_text(body, "sum")
    assert text.startswith('{"a":{"y":-0.0,"z":1e-300},"b":') and text.endswith('"}')
    assert checked_json(text, "sum") == body
    # the layout json.dumps gives by default (what earlier files hold) reads back the same
    assert checked_json(json.dumps(json.loads(text)), "sum") == body
    assert checked_json(checked_text({}, "sha256"), "sha256") == {}
    assert checked_lines((checked_line(body) + checked_line({})).encode(), 10_000) == [body, {}]
    with pytest.raises(ValueError, match="fails its checksum"):
        checked_json(text.replace("1e-300", "2e-300"), "sum")
    with pytest.raises(ValueError, match="already in the body"):
        checked_text({"sum": 1}, "sum")
    with pytest.raises(ValueError):  # canonical JSON has no NaN
        checked_text({"x": float("nan")}, "sum")
