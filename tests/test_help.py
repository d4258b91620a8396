"""Every command's ``--help``: its own page and flags, defaults in one form (``[default …]``)."""
from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from swarm.cli import main

ROOT = Path(__file__).resolve().parents[1]
SWARM_PAGES = [["run"], ["compare"], ["sweep"], ["experiment"], ["experiment", "paper"],
               ["experiment", "terrain"], ["experiment", "drive"], ["deploy"], ["export"],
               ["watch"], ["replay"], ["plot"], ["dem-crop"], ["dem-from-npz"],
               ["agent-config"], []]


def _page(capsys, argv: list[str]) -> str:
    with pytest.raises(SystemExit) as done:
        main([*argv, "--help"])
    assert done.value.code == 0
    return " ".join(capsys.readouterr().out.split())  # argparse wraps lines anywhere


def _one_default_form(page: str) -> None:
    assert "(default" not in page and "default:" not in page, page
    assert not re.search(r"\[default 1 [a-z]+s\]", page), page  # [default 1 agents]


@pytest.mark.parametrize("argv", SWARM_PAGES, ids=lambda a: " ".join(a) or "swarm")
def test_every_swarm_page_shows_defaults_in_one_form(capsys, argv):
    _one_default_form(_page(capsys, argv))


@pytest.mark.parametrize("module", ["world", "agents.leader", "agents.follower"])
def test_every_process_page_shows_defaults_in_one_form(module):
    page = subprocess.run([sys.executable, "-m", module, "--help"], cwd=ROOT, check=True,
                          capture_output=True, text=True, timeout=60).stdout
    assert page.startswith(f"usage: python -m {module} ")  # its name, however it was started
    _one_default_form(" ".join(page.split()))


def test_each_experiment_has_its_own_page_and_flags(capsys):
    from swarm.terrain import TerrainSpec

    paper, terrain, drive = (_page(capsys, ["experiment", name])
                             for name in ("paper", "terrain", "drive"))
    assert "python -m swarm experiment paper" in paper and "--dem" not in paper
    assert "--spacing" not in drive and "--estimators" not in drive and "--dem" in drive
    assert "--scheduler" in paper and "--scheduler" not in terrain  # terrain cannot use one
    assert f"[default {','.join(TerrainSpec.estimators)}]" in terrain.replace("- ", "-")
    assert "[default 1 agent]" in _page(capsys, ["run"])


def test_a_flag_of_another_experiment_is_refused_in_one_line(tmp_path, capsys):
    with pytest.raises(SystemExit) as refused:
        main(["experiment", "paper", "--spacing", "5", "--out", str(tmp_path / "o")])
    assert refused.value.code == 2
    err = capsys.readouterr().err
    assert err.splitlines() == ["python -m swarm experiment paper: error: unrecognized "
                                "arguments: --spacing 5 (python -m swarm experiment paper "
                                "--help lists the options)"]
    assert not (tmp_path / "o").exists()


def test_compare_says_which_follower_seeds_and_noise_its_table_shows():
    from protocol.config import RunConfig
    from swarm.cli import compare_caption

    noisy = RunConfig(followers=3, noise_range=0.02, noise_bearing=0.01, surface="wavy")
    assert compare_caption(noisy, 2, [0, 1, 2]) == (
        "follower 2 of 3, mean over 3 seeds (0, 1, 2); surface wavy, comm period 1.28 s, "
        "40 ticks; noise: range σ 0.02 m, bearing σ 0.01 rad")
    assert compare_caption(RunConfig(), 1, [7]).endswith("mean over 1 seed (7); surface "
                                                         "elliptic, comm period 1.28 s, 40 "
                                                         "ticks; noise-free")


def test_ros2_on_a_core_install_names_the_extra_for_live_topics():
    from protocol.distribution import missing_extra_message

    assert missing_extra_message("ros").startswith("ROS 2 (bags, and live topics with --ros2) "
                                                   "needs the [ros] extra")
