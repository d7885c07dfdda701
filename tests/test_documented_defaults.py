"""Users can read every default: each option's ``--help`` shows it, and each field of the shipped
YAML files carries a comment with its meaning."""

import argparse
import dataclasses
import re
from pathlib import Path

import pytest

from drake_cert.cli import COMMANDS, HelpFormatter, build_parser
from drake_cert.config import Preset, RoadCondition

DATA = Path(__file__).resolve().parents[1] / "drake_cert" / "data"


def command_parser(name: str) -> argparse.ArgumentParser:
    parser = build_parser(name)
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices[name]


@pytest.mark.parametrize("command", list(COMMANDS))
def test_every_option_of_every_command_shows_its_default_in_help(command):
    parser = command_parser(command)
    formatter = HelpFormatter(prog="drake-cert")
    for action in parser._actions:
        if not action.option_strings or isinstance(action, (argparse._HelpAction,
                                                            argparse._VersionAction)):
            continue
        shown = formatter._get_help_string(action) or ""
        assert (action.help or "").strip(), f"{command} {action.option_strings[0]} has no help"
        if action.required or action.default is False:  # required, or an off-by-default flag
            continue
        assert "default" in shown, f"{command} {action.option_strings[0]}: {shown!r}"
    text = parser.format_help()
    assert "(default: " in text


@pytest.mark.parametrize("name", ["vehicle.yaml", "settings.yaml"])
def test_every_field_of_the_shipped_yaml_carries_a_comment(name):
    for line in (DATA / name).read_text().splitlines():
        match = re.match(r"^\s*([a-z0-9_]+):\s*(\S.*)?$", line)
        if match and match.group(2):  # a field with a value (not a section header)
            assert "#" in line, f"{name}: field {match.group(1)!r} has no comment"


def test_every_field_of_the_conditions_file_is_explained_in_a_comment():
    comments = " ".join(line for line in (DATA / "conditions.yaml").read_text().splitlines()
                        if line.lstrip().startswith("#"))
    for schema in (RoadCondition, Preset):
        for field in dataclasses.fields(schema):
            assert field.name in comments, f"conditions.yaml: {field.name} is not explained"
