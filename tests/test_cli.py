"""The CLI dispatcher: usage errors exit 2 with one line, help exits 0; progress in logs."""

import subprocess
import sys
from pathlib import Path

import pytest

from drake_cert import cli


def test_no_command_exits_2(capsys):
    assert cli.main([]) == 2


def test_unknown_command_exits_2_with_one_line():
    out = subprocess.run([sys.executable, "-m", "drake_cert.cli", "fly"],
                         capture_output=True, text=True)
    assert out.returncode == 2
    assert "invalid choice: 'fly'" in out.stderr
    assert "Traceback" not in out.stderr


def test_help_lists_every_command():
    out = subprocess.run([sys.executable, "-m", "drake_cert.cli", "--help"],
                         capture_output=True, text=True)
    assert out.returncode == 0
    for name in cli.COMMANDS:
        assert name in out.stdout


def test_help_speaks_to_a_user_not_a_developer(capsys):
    """The top-level help says what the tool does and where to start, in plain text."""
    try:
        cli.main(["--help"])
    except SystemExit as e:
        assert e.code == 0
    out = " ".join(capsys.readouterr().out.split())  # whatever the terminal's width
    assert "``" not in out  # no reStructuredText from a module docstring
    assert "Certified robust perception-based lateral control" in out
    # the three-command workflow, each command as a user types it
    for line in cli.YOUR_VEHICLE_COMMANDS:
        assert line in out


@pytest.mark.parametrize("document", ["README.md", "docs/usage.md"])
def test_the_three_vehicle_commands_are_the_same_everywhere(document):
    """One version: the block under "Your vehicle in three commands" is the help's, word for
    word (comments aside)."""
    text = (Path(__file__).resolve().parents[1] / document).read_text()
    block = text[text.index("## Your vehicle in three commands"):]
    block = block[block.index("```bash\n") + 8:]
    block = block[:block.index("```")]
    commands = tuple(line.split("#")[0].strip() for line in block.strip().splitlines())
    assert commands == cli.YOUR_VEHICLE_COMMANDS


def test_progress_off_a_terminal_is_ascii_lines_at_most_a_minute_apart(capsys):
    from drake_cert.cli.progress import progress_bar

    with progress_bar(range(5), desc="frames") as bar:  # capsys: stderr is not a terminal
        assert bar.mininterval == 60.0 and bar.ascii
        for _ in bar:
            pass
    err = capsys.readouterr().err
    assert "frames" in err and "5/5" in err
    assert "\r" not in err and err.endswith("\n")  # whole lines: a log shows each at once
    lines = err.splitlines()
    assert lines[0].startswith("frames:   0%") and len(lines) <= 3
