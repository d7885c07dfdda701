"""docs/commands.md is what `drake-cert COMMAND --help` prints: the reference cannot drift."""

from drake_cert.cli import COMMANDS
from drake_cert.cli.reference import PAGE, command_reference


def test_the_committed_reference_is_the_parsers_help():
    made = command_reference()
    assert PAGE.read_text() == made, (
        "docs/commands.md differs from the parsers' help: "
        "run `python -m drake_cert.cli.reference --write`")


def test_every_command_has_its_section():
    text = PAGE.read_text()
    for name in COMMANDS:
        assert f"## drake-cert {name}\n" in text
        assert f"usage: drake-cert {name}" in text
