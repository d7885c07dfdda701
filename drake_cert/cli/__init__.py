"""``drake-cert`` command line: one line and exit code 2 for user mistakes, never a traceback.

Sub-commands live in ``drake_cert.cli.<name>``, imported only when used (so that
``drake-cert verify`` does not import torch). Each module defines ``configure(parser)`` and
``run(args) -> int``. Machine-readable output goes to stdout (``--json``), progress and
messages to stderr.
"""

import argparse
import importlib
import sys

from drake_cert.errors import DrakeCertError

COMMANDS = {
    "synthesize": "synthesize the design table (gains, filter gain, safe speed) for a vehicle",
    "verify": "re-check a saved design or design table by an independent code path",
    "simulate": "simulate the closed loop (plant + L1 adaptive controller) on a curved road",
    "generate": "render synthetic driving frames for a preset and write a sample grid",
    "train": "train a perception model (classifier or regressor) for a preset",
    "certify": "certify a smoothed model on frames, optionally under attack",
}


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # argparse's own error path: one line, exit code 2
        self.print_usage(sys.stderr)
        print(f"{self.prog}: error: {message}", file=sys.stderr)
        sys.exit(2)


def build_parser(command: str | None) -> argparse.ArgumentParser:
    parser = _Parser(prog="drake-cert", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    for name, help_text in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        if name == command:
            importlib.import_module(f"drake_cert.cli.{name}").configure(p)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    command = next((a for a in argv if not a.startswith("-")), None)
    parser = build_parser(command if command in COMMANDS else None)
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help(sys.stderr)
        return 2
    module = importlib.import_module(f"drake_cert.cli.{args.command}")
    try:
        return int(module.run(args) or 0)
    except DrakeCertError as e:
        print(f"drake-cert {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"drake-cert {args.command}: interrupted", file=sys.stderr)
        return 130

