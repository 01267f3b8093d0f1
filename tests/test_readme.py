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
    assert "pytest" in commands[1] and "ruff check" in commands[1]


def test_ci_runs_the_readme_test_command():
    ci_lines = [line.strip() for line in (REPO / ".ci" / "run").read_text().splitlines()]
    assert _readme_commands()[1] in ci_lines


def test_setup_script_is_executable():
    assert (REPO / "setup.sh").stat().st_mode & 0o111


def test_the_library_example_runs_and_finds_the_box():
    """The README's Python example pasted into ``python -`` (standard input: the OpenNI2
    reader must start without the caller's main module), from the checkout."""
    import subprocess
    import sys

    text = (REPO / "README.md").read_text(encoding="utf-8")
    block = text.split("## As a library", 1)[1].split("```python\n", 1)[1].split("```", 1)[0]
    done = subprocess.run([sys.executable, "-"], input=block, cwd=REPO, capture_output=True,
                          text=True, timeout=300,
                          env={**__import__("os").environ, "PYTHONPATH": str(REPO)})
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert lines[0].startswith("changed")
    assert any(line.startswith("appeared") for line in lines[1:]), done.stdout


def test_the_public_api_is_the_package_face():
    import robot_change

    for name in robot_change.__all__:
        assert getattr(robot_change, name) is not None, name
    assert {"build_scene", "detect_changes", "fit_mixture", "emd", "clean_cloud", "SceneModel",
            "ChangeParams", "CloudParams", "Mixture"} <= set(robot_change.__all__)
    with __import__("pytest").raises(AttributeError):
        robot_change.no_such_name  # noqa: B018
