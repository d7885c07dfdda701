"""``drake-cert`` command line: one line and exit code 2 for user mistakes, never a traceback.

Sub-commands live in ``drake_cert.cli.<name>``, imported only when used (so that
``drake-cert verify`` does not import torch). Each module defines ``configure(parser)`` and
``run(args) -> int``, and may define ``check(args)``: the checks of the command's files and
numbers that need no heavy library, run before the command's heavy imports (so a mistake in a
vehicle or scenario file is answered before cvxpy or torch load). Machine-readable output goes
to stdout (``--json``), progress and messages to stderr.
"""

import argparse
import contextlib
import importlib
import signal
import sys

from drake_cert import __version__
from drake_cert.errors import DrakeCertError

DESCRIPTION = ("Certified robust perception-based lateral control: synthesize and verify\n"
               "controller designs, certify perception models, and drive the certified\n"
               "closed loop in Drake.")
YOUR_VEHICLE_COMMANDS = (
    "drake-cert synthesize --vehicle my_car.yaml --out my_designs.yaml",
    "drake-cert verify my_designs.yaml --vehicle my_car.yaml",
    "drake-cert drive --scenario dry_to_snow --compare --attack sa --designs my_designs.yaml "
    "--vehicle my_car.yaml",
)
"""The three-command workflow, the one version the help, the README and docs/usage.md show
(``tests/test_cli.py`` checks the two documents)."""

EPILOG = ("Your vehicle in three commands:\n" + "".join(f"  {c}\n" for c in YOUR_VEHICLE_COMMANDS)
          + """
`drake-cert COMMAND --help` for each command; docs/usage.md for files and units. Mistakes get
one line and exit code 2.""")

COMMANDS = {
    "synthesize": "synthesize the design table (gains, filter gain, safe speed) for a vehicle",
    "verify": "re-check a saved design or design table by an independent code path",
    "simulate": "simulate the closed loop (plant + L1 adaptive controller) on a curved road",
    "generate": "render synthetic driving frames for a preset and write a sample grid",
    "train": "train a perception model (classifier or regressor) for a preset",
    "certify": "certify a smoothed model on frames, optionally under attack",
    "sweep": "train candidate classifiers and pick the one that abstains least without "
             "certifying wrong more",
    "drive": "drive a route in the certified closed-loop Diagram (camera to steering)",
    "calibrate": "draw a scenario model's robust conformal calibration votes and print its "
                 "per-stiffness-bin thresholds",
    "reproduce": "reproduce the paper's tables from per-frame episodes",
}


# Compiled libraries each command needs, imported before it runs with Ctrl-C held back: an
# interrupt that lands inside numpy's or torch's C-extension import leaves the library half
# loaded, and the next import then fails with an ImportError or RecursionError traceback.
HEAVY_IMPORTS = {
    "synthesize": ("numpy", "cvxpy", "pydrake.systems.framework"),
    "verify": ("numpy", "cvxpy", "pydrake.systems.framework"),
    "simulate": ("numpy", "pydrake.systems.analysis"),
    "generate": ("numpy", "torch"),
    "train": ("numpy", "torch"),
    "certify": ("numpy", "torch"),
    "sweep": ("numpy", "torch"),
    "drive": ("numpy", "torch", "cvxpy", "pydrake.systems.analysis"),
    "calibrate": ("numpy", "torch", "pydrake.systems.framework"),
    "reproduce": ("numpy", "torch", "cvxpy", "pydrake.systems.analysis"),
}


@contextlib.contextmanager
def interrupt_deferred():
    """Hold Ctrl-C back inside the block and raise KeyboardInterrupt once it has finished."""
    caught = []
    try:
        previous = signal.signal(signal.SIGINT, lambda *_: caught.append(True))
    except ValueError:  # not the main thread: signals cannot be handled here
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if caught:
        raise KeyboardInterrupt


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Appends "(default: X)" to an option's help unless the help already names its default.

    An option left out with default None says "(default: none)" (nothing written, no check)
    unless its help says in words what happens; flags (default False) are off unless given.
    ``tests/test_documented_defaults.py`` checks that every option of every command shows one.
    """

    def _get_help_string(self, action):
        text = action.help or ""
        default = action.default
        if ("default" in text or default is False or default is argparse.SUPPRESS
                or not action.option_strings or action.required):
            return text
        return f"{text} (default: {'none' if default is None else '%(default)s'})"


# Commands whose noisy sampling runs long: glibc is asked to keep freed memory there
# (certification.sampler.retain_freed_memory), and nowhere else (not in a notebook kernel).
LONG_SAMPLING = ("certify", "drive", "calibrate", "reproduce")


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # argparse's own error path: one line (no usage), exit code 2
        print(f"{self.prog}: error: {message} (see {self.prog} --help)", file=sys.stderr)
        sys.exit(2)


def build_parser(command: str | None) -> argparse.ArgumentParser:
    parser = _Parser(prog="drake-cert", description=DESCRIPTION, epilog=EPILOG,
                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    for name, help_text in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text,
                           formatter_class=HelpFormatter)
        if name == command:
            importlib.import_module(f"drake_cert.cli.{name}").configure(p)
    return parser


def refuse_empty_values(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """One line, exit 2, for an option given an empty value (``--vehicle ''``, often an unset
    shell variable): no option of any command means anything by it, and taking it for "left
    out" would run on the shipped files instead of the user's."""
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    command_parser = sub.choices[args.command]
    for action in command_parser._actions:
        if not action.option_strings:
            continue
        value = getattr(args, action.dest, None)
        if value == action.default:  # left out (an option whose default is empty text)
            continue
        values = value if isinstance(value, list) else [value]
        if any(isinstance(v, str) and not v.strip() for v in values):
            from drake_cert.errors import ConfigError

            raise ConfigError(f"argument {action.option_strings[-1]}: empty value (an unset "
                              "shell variable?); give one or leave the option out")


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    command = next((a for a in argv if not a.startswith("-")), None)
    try:  # Ctrl-C anywhere, also while a command imports torch or pydrake: one line
        parser = build_parser(command if command in COMMANDS else None)
        args = parser.parse_args(argv)
        if args.command is None:
            parser.print_help(sys.stderr)
            return 2
        refuse_empty_values(parser, args)
        module = importlib.import_module(f"drake_cert.cli.{args.command}")
        with interrupt_deferred():
            if hasattr(module, "check"):
                module.check(args)  # files and numbers first: a mistake costs no heavy import
            for name in HEAVY_IMPORTS.get(args.command, ("numpy",)):
                importlib.import_module(name)
        if args.command in LONG_SAMPLING:
            from drake_cert.certification.sampler import retain_freed_memory

            retain_freed_memory()
        return int(module.run(args) or 0)
    except DrakeCertError as e:
        print(f"drake-cert {command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"drake-cert {command or ''}: interrupted".replace(" :", ":"), file=sys.stderr)
        return 130

