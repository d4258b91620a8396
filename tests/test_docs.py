"""The README and ``docs/`` stay usable: a short README with a working table of contents, links
and images that point at files of this repository, and a quick start in step with CI."""
from __future__ import annotations

import re
import unicodedata
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
CI = ROOT / ".ci" / "run"
DOCS = sorted([README, *(ROOT / "docs").rglob("*.md")])
MAX_README_LINES = 500

FENCE = re.compile(r"^\s*(```|~~~)")
LINK = re.compile(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
INLINE_CODE = re.compile(r"(`+).+?\1")
SCHEME = re.compile(r"^[a-zA-Z][a-zA-Z0-9+.-]*:")
FIRST_COMMAND = re.compile(
    r"python3 -m venv \.venv && \.venv/bin/pip install -e '?\.(\[[a-z,]+\])?'? && "
    r"\.venv/bin/python -m swarm run")
TEST_COMMAND = re.compile(r"test command `([^`]+)`")


def prose_lines(text: str) -> list[str]:
    """The lines of a markdown text outside fenced code blocks."""
    out, fenced = [], False
    for line in text.splitlines():
        if FENCE.match(line):
            fenced = not fenced
            continue
        if not fenced:
            out.append(line)
    return out


def fenced_blocks(lines: list[str]) -> list[tuple[str, str]]:
    """The fenced code blocks among ``lines``: (info string, contents stripped)."""
    blocks: list[tuple[str, str]] = []
    info, current = "", None
    for line in lines:
        if FENCE.match(line):
            if current is None:
                info, current = line.strip().strip("`~").strip(), []
            else:
                blocks.append((info, "\n".join(current).strip()))
                current = None
        elif current is not None:
            current.append(line)
    return blocks


def slug(heading: str) -> str:
    """The anchor GitHub gives a heading: lower case, punctuation dropped (letters, digits,
    ``-`` and ``_`` kept), spaces to hyphens.

    >>> slug("The paper's experiments")
    'the-papers-experiments'
    >>> slug("Comparing estimators: `compare` and `sweep`")
    'comparing-estimators-compare-and-sweep'
    >>> slug("1. What the system does")
    '1-what-the-system-does'
    """
    text = heading.strip().lower()
    kept = "".join(c for c in text if c in " -_" or unicodedata.category(c)[0] in "LN")
    return kept.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """Every heading anchor of a markdown file (repeated headings numbered as GitHub does)."""
    seen: dict[str, int] = {}
    out = set()
    for line in prose_lines(path.read_text(encoding="utf-8")):
        match = re.match(r"^#{1,6}\s+(.*?)\s*#*\s*$", line)
        if not match:
            continue
        base = slug(match.group(1))
        count = seen.get(base, 0)
        seen[base] = count + 1
        out.add(base if count == 0 else f"{base}-{count}")
    return out


def links(path: Path) -> list[str]:
    """Every link and image target in a markdown file's prose (not in code)."""
    targets = []
    for line in prose_lines(path.read_text(encoding="utf-8")):
        targets += LINK.findall(INLINE_CODE.sub("", line))
    return targets


def section(path: Path, title: str) -> list[str]:
    """The lines of the level-2 section ``title`` of a markdown file, code blocks included."""
    lines = path.read_text(encoding="utf-8").splitlines()
    start = lines.index(f"## {title}") + 1
    end = next((i for i in range(start, len(lines)) if lines[i].startswith("## ")), len(lines))
    return lines[start:end]


def test_readme_is_short():
    n = len(README.read_text(encoding="utf-8").splitlines())
    assert n <= MAX_README_LINES, f"README.md has {n} lines (at most {MAX_README_LINES})"


def test_readme_contents_lists_every_section_and_resolves():
    toc = [t for line in section(README, "Contents") for t in LINK.findall(line)]
    assert len(toc) >= 5, toc
    assert all(t.startswith("#") for t in toc), toc
    headings = anchors(README)
    assert [t for t in toc if t[1:] not in headings] == []
    level2 = [slug(line[3:]) for line in prose_lines(README.read_text(encoding="utf-8"))
              if line.startswith("## ") and line != "## Contents"]
    assert [h for h in level2 if f"#{h}" not in toc] == []


@pytest.mark.parametrize("path", DOCS, ids=[str(p.relative_to(ROOT)) for p in DOCS])
def test_relative_links_and_images_point_at_files_of_this_repository(path):
    broken = []
    for target in links(path):
        if SCHEME.match(target):
            continue
        file_part, _, anchor = target.partition("#")
        dest = (path.parent / file_part).resolve() if file_part else path
        if ROOT not in dest.parents and dest != ROOT:
            broken.append(f"{target}: outside the repository")
        elif not dest.exists():
            broken.append(f"{target}: no such file")
        elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
            broken.append(f"{target}: no heading '{anchor}' in {dest.relative_to(ROOT)}")
    assert broken == []


@pytest.mark.parametrize("path", DOCS, ids=[str(p.relative_to(ROOT)) for p in DOCS])
def test_nothing_points_outside_the_repository(path):
    assert "../shared" not in path.read_text(encoding="utf-8")


def test_quick_start_is_two_commands_and_the_second_is_ci():
    commands = [code for info, code in fenced_blocks(section(README, "Quick start"))
                if info == "bash"]
    assert len(commands) == 2, commands
    assert FIRST_COMMAND.fullmatch(commands[0]), commands[0]
    assert commands[1] == f"bash {CI.relative_to(ROOT)}"
    assert CI.is_file()


def test_ci_runs_the_readme_test_command():
    quick_start = "\n".join(section(README, "Quick start"))
    named = TEST_COMMAND.findall(" ".join(quick_start.split()))
    assert len(named) == 1, named
    ci_lines = [line.strip() for line in CI.read_text(encoding="utf-8").splitlines()]
    assert named[0] in ci_lines


def test_ci_lints_before_the_tests():
    """``ruff check .`` (its rules in pyproject.toml) runs first: a lint error fails CI fast."""
    ci_lines = [line.strip() for line in CI.read_text(encoding="utf-8").splitlines()]
    assert ".venv/bin/ruff check ." in ci_lines
    assert ci_lines.index(".venv/bin/ruff check .") < ci_lines.index(".venv/bin/python -m pytest")
    assert "[tool.ruff" in (ROOT / "pyproject.toml").read_text(encoding="utf-8")


def test_ci_installs_system_packages_only_as_root(tmp_path):
    """``.ci/run`` calls apt-get only as root; anyone else is told what to install and the
    browser tests skip with that reason. Its browser block runs here with a PATH of stubs:
    ``chromium`` missing, ``id -u`` a user's, ``apt-get`` recording any call."""
    import subprocess

    text = CI.read_text(encoding="utf-8")
    start, end = text.index("if ! command -v chromium"), text.index("rm -rf .venv")
    block = text[start:end]
    stubs = tmp_path / "bin"
    stubs.mkdir()
    fakes = {"id": 'echo "${FAKE_UID}"', "apt-get": 'echo apt-get "$@" >> "$CALLS"'}
    for name, body in fakes.items():
        (stubs / name).write_text(f"#!/bin/sh\n{body}\n")
        (stubs / name).chmod(0o755)
    calls = tmp_path / "calls"
    script = block + 'echo "skip reason: ${SWARM_NO_BROWSER:-}"\n'
    env = {"PATH": str(stubs), "CALLS": str(calls)}
    user = subprocess.run(["/bin/bash", "-c", script], env={**env, "FAKE_UID": "1000"},
                          capture_output=True, text=True, timeout=30)
    assert user.returncode == 0, user.stderr
    assert not calls.exists()
    assert "sudo apt-get install chromium" in user.stderr
    assert "skip reason: chromium is not installed and .ci/run is not root" in user.stdout
    root = subprocess.run(["/bin/bash", "-c", script], env={**env, "FAKE_UID": "0"},
                          capture_output=True, text=True, timeout=30)
    assert root.returncode == 0, root.stderr
    assert "install -y -qq chromium" in calls.read_text()
