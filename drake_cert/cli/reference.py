"""The command reference, docs/commands.md, made from the parsers the command line runs.

``python -m drake_cert.cli.reference`` prints it; ``--write`` replaces docs/commands.md
(atomically); ``tests/test_command_reference.py`` fails when the committed page and the parsers
differ, so the reference cannot drift from ``drake-cert COMMAND --help``. The help is formatted
at a fixed width (100 columns) so the page does not depend on the terminal that made it.
"""

import argparse
import os
import sys
from pathlib import Path

from drake_cert.cli import COMMANDS, build_parser
from drake_cert.io import atomic_write_text

WIDTH = 100
PAGE = Path(__file__).resolve().parents[2] / "docs" / "commands.md"
INTRO = """\
# Command reference

Generated from the parsers `drake-cert` runs (`python -m drake_cert.cli.reference --write`;
`tests/test_command_reference.py` fails when this page and `drake-cert COMMAND --help` differ).
What each command writes, prints and refuses, with examples: [usage.md](usage.md).
"""


def _help(parser: argparse.ArgumentParser) -> str:
    """``parser``'s help at WIDTH columns, whatever the terminal."""
    before = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = str(WIDTH + 2)  # argparse leaves two columns free
    try:
        return parser.format_help().rstrip()
    finally:
        if before is None:
            del os.environ["COLUMNS"]
        else:
            os.environ["COLUMNS"] = before


def _subparser(parser: argparse.ArgumentParser, name: str) -> argparse.ArgumentParser:
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return action.choices[name]


def command_reference() -> str:
    """The Markdown page: the top-level help, then each command's, in the order of COMMANDS."""
    parts = [INTRO, "## drake-cert\n", "```", _help(build_parser(None)), "```\n"]
    for name in COMMANDS:
        parts += [f"## drake-cert {name}\n", "```",
                  _help(_subparser(build_parser(name), name)), "```\n"]
    return "\n".join(parts)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    text = command_reference()
    if argv == ["--write"]:
        atomic_write_text(PAGE, text)
        print(f"wrote {PAGE}", file=sys.stderr)
    elif not argv:
        sys.stdout.write(text)
    else:
        print("usage: python -m drake_cert.cli.reference [--write]", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
