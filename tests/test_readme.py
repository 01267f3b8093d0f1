"""The README's two commands are the ones CI runs and the ones that exist."""

from __future__ import annotations

import re

from conftest import REPO


def _readme_commands() -> list[str]:
    text = (REPO / "README.md").read_text(encoding="utf-8")
    first_block = re.search(r"```sh\n(.*?)```", text, re.S)
    assert first_block, "README must open with a ```sh block holding the two commands"
    before = text[: first_block.start()]
    assert before.count("\n") <= 2, "the two commands must open the README"
    return [line for line in first_block.group(1).splitlines() if line.strip()]


def test_readme_opens_with_exactly_two_commands():
    commands = _readme_commands()
    assert len(commands) == 2
    assert "robot-change demo" in commands[0]
    assert "pytest" in commands[1]


def test_ci_runs_the_readme_test_command():
    ci_lines = [line.strip() for line in (REPO / ".ci" / "run").read_text().splitlines()]
    assert _readme_commands()[1] in ci_lines


def test_setup_script_is_executable():
    assert (REPO / "setup.sh").stat().st_mode & 0o111
