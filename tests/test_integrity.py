"""A run's record cannot be corrupted (design §7): one writer per results folder, whole rows only
(a full disk included), readers and ``--resume`` that refuse a damaged record, nothing written
through a symbolic link.

Races are started with gaps drawn from a printed seed (``FAULT_SEED=...`` replays them). Every
process is ended by its own handle; every wait is bounded.
"""
from __future__ import annotations

import errno
import json
import os
import random
import resource
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

import swarm.cli
from protocol.config import RunConfig, dump_config
from protocol.folder import (
    LOCK_FILE,
    AppendFile,
    FolderBusy,
    FolderLock,
    FolderRefused,
    SymlinkRefused,
    check_out_dir,
    open_file,
    write_atomic,
)
from protocol.record import DamagedRecord, read_controls, read_observations, read_ticks
from protocol.session import free_tcp_endpoint
from swarm.launch import agent_commands, launch, write_briefs
from swarm.local import run_local
from tests.waiting import Procs, wait_for
from world import checkpoint

ROOT = Path(__file__).resolve().parents[1]
SEED = int(os.environ.get("FAULT_SEED", str(int(time.time()) % 100_000)))
RACES = [0, 1]
"""Repetitions of each race, each with its own drawn start gap (both in the slow tier; fast
tier: a second writer is refused while the holder lives)."""
WAIT_S = 90.0


@pytest.fixture
def procs():
    p = Procs()
    yield p
    p.close()


def _error_line(err: str) -> str:
    """stderr must be one line starting with ``error:``, no traceback; return it."""
    lines = [line for line in err.strip("\n").split("\n") if line]
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert "Traceback" not in err, err
    return lines[0]


def _outcomes(*procs: subprocess.Popen, timeout: float = WAIT_S) -> list[tuple[int, str]]:
    return [(p.wait(timeout=timeout), p.communicate(timeout=10)[1]) for p in procs]


# --- one writer per folder ----------------------------------------------------------------------

HOLD = """
import sys, time
from protocol.folder import FolderLock
lock = FolderLock(sys.argv[1], "holder").acquire()
print("held", flush=True)
time.sleep(120)
"""


def test_a_second_writer_is_refused_while_the_holder_lives_even_stalled(tmp_path, procs):
    folder = tmp_path / "out"
    holder = procs.python("-c", HOLD, str(folder))
    assert holder.stdout.readline() == "held\n"
    names = f"run 'holder' (pid {holder.pid} on host {socket.gethostname()!r})"
    with pytest.raises(FolderBusy) as refused:
        FolderLock(folder, "second").acquire()
    assert f"is in use by {names}" in str(refused.value)
    holder.send_signal(signal.SIGSTOP)  # stalled, not dead: its lock stands
    try:
        with pytest.raises(FolderBusy):
            FolderLock(folder, "second").acquire()
    finally:
        holder.send_signal(signal.SIGCONT)
    holder.kill()  # dead: the kernel released its lock, the stale note is overwritten
    holder.wait(timeout=10)
    with FolderLock(folder, "third"):
        note = json.loads((folder / LOCK_FILE).read_text())
        assert note == {"run_id": "third", "pid": os.getpid(), "host": socket.gethostname()}
    with FolderLock(folder, "fourth"):  # released on leaving the block
        pass


@pytest.mark.slow  # processes racing for one folder (see RACES)
@pytest.mark.parametrize("n", RACES)
def test_two_runs_started_together_one_is_refused_at_once(tmp_path, procs, n):
    print(f"FAULT_SEED={SEED} (rerun with this environment variable to replay)")
    out, gap = tmp_path / f"race-{n}", random.Random(f"{SEED}-runs-{n}").uniform(0.0, 0.3)
    print(f"race {n}: second run started {gap:.3f} s after the first")
    runs = []
    for name, seed in (("a", 1), ("b", 2)):
        # paced by the wall clock (about 4 s, little CPU): the first still writes when the
        # second starts
        runs.append(procs.python("-m", "swarm", "run", "--in-process", "--ticks", "150",
                                 "--mode", "realtime", "--time-scale", "0.02",
                                 "--seed", str(seed), "--run-id", f"race-{n}-{name}",
                                 "--out", str(out)))
        time.sleep(gap)
    (code_a, err_a), (code_b, err_b) = _outcomes(*runs)
    winner, loser = (0, 1) if code_b == 2 else (1, 0)
    assert (code_a, code_b)[loser] == 2, (err_a, err_b)
    # the winner ran to the end: a success, unless a tick it missed under this pace left its
    # follower out of formation (design §7), which its verdict then says
    summary = json.loads((out / "summary.json").read_text())
    assert (code_a, code_b)[winner] == (1 if summary["formation_broken"] else 0), (err_a, err_b)
    line = _error_line((err_a, err_b)[loser])
    assert (f"is in use by run 'race-{n}-{'ab'[winner]}' (pid {runs[winner].pid} on host "
            in line), line
    assert summary["run_id"] == f"race-{n}-{'ab'[winner]}" and summary["complete"]
    assert f'run_id = "race-{n}-{"ab"[winner]}"' in (out / "config.toml").read_text()
    rows = read_ticks(out / "ticks.csv")  # whole, ordered, no (tick, agent) twice
    observations = read_observations(out / "observations.csv")  # a realtime miss has none
    assert len(rows) == 2 * 150 and 0 < len(observations) <= 150


def _resumable(tmp_path: Path, procs: Procs, config: RunConfig) -> Path:
    """A results folder a world started and was killed in before any agent came."""
    folder = tmp_path / "prepared"
    folder.mkdir()
    dump_config(config, folder / "config.toml")
    world = procs.python("-m", "world", "--config", str(folder / "config.toml"), "--out",
                        str(folder), "--listen", free_tcp_endpoint())
    wait_for(lambda: (folder / checkpoint.STATE_FILE).exists(), WAIT_S, "the first checkpoint")
    world.kill()
    world.wait(timeout=10)
    return folder


@pytest.mark.slow  # processes racing for one folder (see RACES)
@pytest.mark.parametrize("n", RACES)
def test_two_resumes_or_a_run_and_a_resume_one_is_refused(tmp_path, procs, n):
    """Two ``--resume`` of one folder, or a fresh ``--force`` run and a resume, started together:
    one refuses at once naming the other; two resumes: the other completes the run with the
    numbers of an undisturbed one."""
    print(f"FAULT_SEED={SEED} (rerun with this environment variable to replay)")
    rng = random.Random(f"{SEED}-resumes-{n}")
    config = RunConfig(run_id="resume-race", followers=2, ticks=60, start_timeout=60.0)
    reference = tmp_path / "reference"
    run_local(config, reference)
    prepared = _resumable(tmp_path, procs, config)
    for kind in ("two resumes", "run and resume"):
        folder, gap = tmp_path / f"{kind.replace(' ', '-')}-{n}", rng.uniform(0.0, 0.3)
        print(f"{kind} {n}: second started {gap:.3f} s after the first")
        shutil.copytree(prepared, folder)
        firsts = (["--resume", str(folder)] if kind == "two resumes" else
                  ["--config", str(folder / "config.toml"), "--out", str(folder), "--force"])
        endpoints = [free_tcp_endpoint(), free_tcp_endpoint()]
        worlds = []
        for source, endpoint in ((firsts, endpoints[0]),
                                 (["--resume", str(folder)], endpoints[1])):
            worlds.append(procs.python("-m", "world", *source, "--listen", endpoint))
            time.sleep(gap)
        wait_for(lambda ws=worlds: any(w.poll() is not None for w in ws), 30,
                 "one world to end")
        loser = 0 if worlds[0].poll() is not None else 1
        winner = 1 - loser
        code, err = _outcomes(worlds[loser])[0]
        assert code == 2, err
        line = _error_line(err)
        assert f"is in use by run 'resume-race' (pid {worlds[winner].pid} on" in line, line
        assert worlds[winner].poll() is None  # the holder goes on, untouched
        if kind == "run and resume":
            worlds[winner].kill()
            continue
        agents = [procs.python(*cmd[1:]) for cmd in agent_commands(
            write_briefs(config, folder), endpoints[winner], config.followers)]
        code, err = _outcomes(worlds[winner])[0]
        assert code == 0, err
        for agent in agents:
            assert agent.wait(timeout=WAIT_S) == 0
        for name in ("ticks.csv", "observations.csv"):
            assert (folder / name).read_bytes() == (reference / name).read_bytes()


# --- whole rows ---------------------------------------------------------------------------------

def test_a_short_write_is_cut_back_to_the_last_whole_record(tmp_path):
    """A file-size limit makes the kernel accept part of a write, then refuse the rest, as a
    disk filling up does: the append is undone and the error names the file."""
    log = AppendFile(tmp_path / "rows.csv", truncate=True)
    log.append(b"a,b\n1,2\n")
    limit = resource.getrlimit(resource.RLIMIT_FSIZE)
    handler = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    try:
        resource.setrlimit(resource.RLIMIT_FSIZE, (log.size + 5, limit[1]))
        with pytest.raises(OSError) as exc:
            log.append(b"3,4\n" * 100)
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, limit)
        signal.signal(signal.SIGXFSZ, handler)
    assert exc.value.errno == errno.EFBIG and exc.value.filename == str(tmp_path / "rows.csv")
    assert (tmp_path / "rows.csv").read_bytes() == b"a,b\n1,2\n"
    log.append(b"5,6\n")  # and the next append goes on from there
    log.close()
    assert (tmp_path / "rows.csv").read_bytes() == b"a,b\n1,2\n5,6\n"


class Stop(Exception):
    """Ends a run from its progress callback, as a crash would: the checkpoint stays."""


def _stopped_run(folder: Path, config: RunConfig, after: int) -> None:
    def on_tick(tick: int) -> None:
        if tick >= after:
            raise Stop

    with pytest.raises(Stop):
        launch(config, folder, in_process=True, on_tick=on_tick)


def _damage(kind: str, text: str) -> str:
    lines = text.split("\n")
    if kind == "torn":
        return text[:-7]
    if kind == "glued":  # two rows on one line
        return "\n".join(lines[:3] + [lines[3] + "," + lines[4]] + lines[5:])
    if kind == "out of order":
        return "\n".join(lines[:3] + [lines[5], lines[4], lines[3]] + lines[6:])
    return "\n".join(lines[:4] + [lines[3]] + lines[4:])  # a duplicated row


DAMAGES = ("torn", "glued", "out of order", "duplicate")


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("finished") / "run"
    launch(RunConfig(run_id="finished", followers=2, ticks=20), folder, in_process=True)
    return folder


@pytest.mark.parametrize("kind", DAMAGES)
def test_readers_refuse_a_damaged_record_in_one_line(finished_run, tmp_path, capsys, kind):
    folder = tmp_path / "run"
    shutil.copytree(finished_run, folder)
    (folder / "ticks.csv").write_text(_damage(kind, (folder / "ticks.csv").read_text()))
    with pytest.raises(DamagedRecord, match=r"ticks\.csv, line \d+: .*damaged"):
        read_ticks(folder / "ticks.csv")
    assert swarm.cli.main(["plot", str(folder)]) == 2
    assert "ticks.csv, line" in _error_line(capsys.readouterr().err)
    assert swarm.cli.main(["replay", str(folder), "--live-port", "0"]) == 2
    assert "ticks.csv, line" in _error_line(capsys.readouterr().err)
    (folder / "ticks.csv").write_bytes((finished_run / "ticks.csv").read_bytes())
    (folder / "observations.csv").write_text(
        _damage(kind, (folder / "observations.csv").read_text()))
    with pytest.raises(DamagedRecord, match=r"observations\.csv, line \d+"):
        read_observations(folder / "observations.csv")


@pytest.fixture(scope="module")
def finished_drive_run(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("finished-drive") / "run"
    launch(RunConfig(run_id="finished-drive", followers=2, ticks=6, motion="drive",
                     control_steps=4, snap_steps=2), folder, in_process=True)
    return folder


@pytest.mark.parametrize("kind", DAMAGES)
def test_a_damaged_controls_csv_is_refused_in_one_line(finished_drive_run, tmp_path, capsys,
                                                       kind):
    """A drive run's ``controls.csv``: its reader and ``swarm export`` refuse a torn, glued,
    reordered or repeated row (exit 2, one line naming the file and line)."""
    folder = tmp_path / "run"
    shutil.copytree(finished_drive_run, folder)
    assert len(read_controls(folder / "controls.csv")) == 6 * 2 * 6
    (folder / "controls.csv").write_text(_damage(kind, (folder / "controls.csv").read_text()))
    with pytest.raises(DamagedRecord, match=r"controls\.csv, line \d+: .*damaged"):
        read_controls(folder / "controls.csv")
    assert swarm.cli.main(["export", str(folder)]) == 2
    assert "controls.csv, line" in _error_line(capsys.readouterr().err)
    assert not (folder / "bag").exists()


def _edit_checkpoint(folder: Path, change) -> None:
    """Rewrite the checkpoint with ``change`` applied and a recomputed checksum."""
    body = json.loads((folder / checkpoint.STATE_FILE).read_text())
    body.pop("sha256")
    change(body)
    checkpoint.save(folder, run_id=body["run_id"], start=body["start"], sim=body["sim"],
                    offsets=body["offsets"], wall_time=body["wall_time"])


@pytest.mark.parametrize("defect", ["offset mid-row", "damaged kept row", "controls mid-row",
                                    "crafted journal line"])
def test_resume_changes_nothing_until_everything_is_validated(tmp_path, procs, defect):
    """A checkpoint offset into the middle of a row, or a damaged row before the offset:
    ``--resume`` refuses in one line and every file is as it was (it used to cut ticks.csv
    first, then crash); in a drive run, ``controls.csv``'s offset too; and a request journal
    with a line the world did not write."""
    folder = tmp_path / "run"
    drive = {"motion": "drive"} if defect == "controls mid-row" else {}
    _stopped_run(folder, RunConfig(run_id="resume-check", followers=1, ticks=40, **drive),
                 after=12)
    damaged = "controls.csv" if drive else "ticks.csv"
    if defect == "crafted journal line":  # a whole line, but not the world's
        damaged = checkpoint.JOURNAL_FILE
        with open(folder / damaged, "ab") as journal:
            journal.write(b'{"agent": 1, "tick": 99, "index": 0, "request": {"sense": true}, '
                          b'"sum": "0000"}\n')
    elif defect in ("offset mid-row", "controls mid-row"):
        _edit_checkpoint(folder, lambda body: body["offsets"].update(
            {damaged: body["offsets"][damaged] - 9}))
    else:
        text = (folder / "ticks.csv").read_text()
        (folder / "ticks.csv").write_text(_damage("duplicate", text))
        _edit_checkpoint(folder, lambda body: body["offsets"].update(
            {"ticks.csv": body["offsets"]["ticks.csv"] + len(text.split("\n")[3]) + 1}))
    def files() -> dict[str, bytes]:  # the lock file's note names its latest holder
        return {p.name: p.read_bytes() for p in folder.iterdir()
                if p.is_file() and p.name != LOCK_FILE}

    before = files()
    world = procs.python("-m", "world", "--resume", str(folder), "--listen", free_tcp_endpoint())
    code, err = _outcomes(world)[0]
    assert code == 2  # refused before anything ran
    line = _error_line(err)
    assert line.startswith(f"error: cannot resume {folder}: {folder / damaged}"), line
    assert files() == before


@pytest.fixture
def small_disk(tmp_path):
    """A 256 KiB tmpfs mounted for the test (skipped where mounting is not permitted)."""
    mount = tmp_path / "disk"
    mount.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(mount)],
                          capture_output=True, text=True, timeout=30)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({done.stderr.strip() or done.returncode}): "
                    "the full-disk test needs root or CAP_SYS_ADMIN")
    try:
        yield mount
    finally:
        subprocess.run(["umount", str(mount)], capture_output=True, timeout=30)


@pytest.mark.slow  # a real full disk; fast tier: test_failures.py (a failing results disk's
# true reason) and test_a_short_write_is_cut_back_to_the_last_whole_record
@pytest.mark.parametrize("layout", ["--in-process", "--processes"])
def test_a_full_disk_leaves_whole_rows_and_the_true_reason(small_disk, procs, layout):
    out = small_disk / "run"
    run = procs.python("-m", "swarm", "run", layout, "--followers", "2", "--ticks", "100000",
                      "--run-id", "full", "--out", str(out))
    code, err = _outcomes(run, timeout=300)[0]
    assert code == 1, err
    line = _error_line(err)
    assert line.startswith(f"error: cannot write the results in {out}: No space left on device: "
                           f"{out}/"), line
    failed = Path(line.rsplit(": ", 1)[1]).name
    summary = json.loads((out / "summary.json").read_text())
    assert summary["complete"] is False
    assert summary["reason"] == f"cannot write {failed}: No space left on device"
    rows = read_ticks(out / "ticks.csv")  # every row whole and in order
    assert (out / "ticks.csv").read_bytes().endswith(b"\n")
    assert len(rows) == 3 * summary["ticks_completed"]
    assert len(read_observations(out / "observations.csv")) == 2 * summary["ticks_completed"]
    for command in (["plot", str(out)], ["replay", str(out), "--live-port", "0"]):
        if command[0] == "replay":  # it would serve the page: only its loading is checked
            from swarm.live.store import load_run

            assert load_run(out).snapshot().frames
            continue
        done = subprocess.run([sys.executable, "-m", "swarm", *command], cwd=ROOT,
                              capture_output=True, text=True, timeout=120)
        assert "Traceback" not in done.stderr
        if done.returncode:  # the full disk may refuse the figures: said in one line
            assert "No space left on device" in _error_line(done.stderr)


# --- nothing outside the folder -----------------------------------------------------------------

def test_a_planted_symlink_is_refused_and_its_target_untouched(tmp_path):
    victim = tmp_path / "victim"
    victim.write_text("precious\n")
    out = tmp_path / "o"
    (out / "logs").mkdir(parents=True)
    (out / "logs" / "agent-1.log").symlink_to("../../victim")
    done = subprocess.run([sys.executable, "-m", "swarm", "run", "--processes", "--out",
                           str(out)], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 2
    line = _error_line(done.stderr)
    assert f"{out / 'logs' / 'agent-1.log'} -> ../../victim" in line, line
    assert victim.read_text() == "precious\n"
    assert sorted(p.name for p in out.iterdir()) == [LOCK_FILE, "logs"]


@pytest.mark.parametrize("command", [["world"], ["swarm", "run"]])
def test_a_symlinked_results_folder_is_refused(tmp_path, command):
    real = tmp_path / "real"
    real.mkdir()
    (tmp_path / "link").symlink_to(real)
    config = tmp_path / "run.toml"
    dump_config(RunConfig(run_id="linked"), config)
    flags = (["--config", str(config), "--listen", free_tcp_endpoint()] if command == ["world"]
             else ["--in-process"])
    done = subprocess.run([sys.executable, "-m", *command, *flags, "--out",
                           str(tmp_path / "link")], cwd=ROOT, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 2
    assert "is a symbolic link" in _error_line(done.stderr)
    assert list(real.iterdir()) == []


def test_the_out_check_refuses_a_symlink_before_writing_through_it(tmp_path):
    """``--out`` as a link, to a folder or to nothing: refused as a link, and nothing (not even
    the writability probe) is created at its target."""
    real = tmp_path / "real"
    real.mkdir()
    (tmp_path / "link").symlink_to(real)
    (tmp_path / "dangling").symlink_to(tmp_path / "missing")
    for link in (tmp_path / "link", tmp_path / "dangling"):
        with pytest.raises(FolderRefused, match=f"--out {link} is a symbolic link"):
            check_out_dir(link)
    assert list(real.iterdir()) == [] and not (tmp_path / "missing").exists()
    assert check_out_dir(tmp_path / "new" / "run") == tmp_path / "new" / "run"
    assert list((tmp_path / "new" / "run").iterdir()) == []  # the probe is gone


def test_no_writer_follows_a_symlink(tmp_path):
    """The helpers every writer uses: a link as the file, or as its folder, is refused."""
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "file").write_text("kept\n")
    run = tmp_path / "run"
    run.mkdir()
    (run / "summary.json").symlink_to(outside / "file")
    (run / "state").symlink_to(outside)
    with pytest.raises(SymlinkRefused):
        write_atomic(run / "summary.json", "{}\n")
    with pytest.raises(SymlinkRefused):
        write_atomic(run / "state" / "agent-1.state", "x\n")
    with pytest.raises(SymlinkRefused):
        AppendFile(run / "summary.json")
    with pytest.raises(SymlinkRefused):
        open_file(run / "state" / "new.log", os.O_WRONLY | os.O_CREAT)
    with pytest.raises(FolderRefused, match="symbolic link"):
        FolderLock(run, "x").acquire()
    assert sorted(p.name for p in outside.iterdir()) == ["file"]
    assert (outside / "file").read_text() == "kept\n"
