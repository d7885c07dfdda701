"""examples/ci runs what it says: the verify command of the GitHub Actions workflow and of the
pre-commit hook, read from their YAML, passes a good design table and fails one that lacks a
design (exit 0 and 1), and the hook script hands its arguments to ``drake-cert``."""

import dataclasses
import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from drake_cert import cli
from drake_cert.config import Preset, default_path, load_conditions
from drake_cert.synthesis.design_io import dump_design_table
from drake_cert.synthesis.table import design_label_ranges

ROOT = Path(__file__).resolve().parents[1]
CI = ROOT / "examples" / "ci"
# the example's conditions: the shipped ones with one preset of two labels (three label ranges)
PRESET = {"name": "rain-to-snow", "labels": ["rain", "snow"], "frames_per_class": 100}


def workflow_commands() -> list[list[str]]:
    """Every ``drake-cert verify`` line of the workflow's ``run`` steps, split as a shell would."""
    workflow = yaml.safe_load((CI / "verify-designs.yml").read_text())
    out = []
    for job in workflow["jobs"].values():
        for step in job["steps"]:
            script = step.get("run", "").replace("\\\n", " ")
            out += [shlex.split(line) for line in script.splitlines()
                    if line.strip().startswith("drake-cert verify")]
    return out


def hook() -> dict:
    config = yaml.safe_load((CI / ".pre-commit-config.yaml").read_text())
    (only,) = [h for repo in config["repos"] for h in repo["hooks"]]
    return only


def hook_command() -> list[str]:
    """The command the pre-commit hook runs: its script execs ``drake-cert`` with its args
    (``pass_filenames: false``: nothing is appended)."""
    h = hook()
    assert h["entry"] == "examples/ci/pre-commit-hook.sh" and h["pass_filenames"] is False
    return ["drake-cert", *h["args"]]


def _paths(argv: list[str]) -> dict[str, str]:
    """``{"design": ..., "vehicle": ..., "settings": ..., "conditions": ...}`` of a command."""
    out, positional, args = {}, [], argv[2:]
    while args:
        if args[0] in ("--vehicle", "--settings", "--conditions"):
            out[args[0][2:]], args = args[1], args[2:]
        else:
            if not args[0].startswith("-"):
                positional.append(args[0])
            args = args[1:]
    (out["design"],) = positional
    return out


@pytest.fixture(scope="module")
def example(default_design_table):
    """(conditions YAML, a complete design table, the same without its snow design): the
    shipped conditions with :data:`PRESET` as their one preset and the session's synthesized
    designs of its ranges, with their switching certificate (the cut table keeps it: a
    certificate covering more designs than the table holds still proves their switching)."""
    from drake_cert.synthesis.design_io import with_switching_certificates

    conditions = dataclasses.replace(load_conditions(), presets=[Preset(**PRESET)])
    ranges = design_label_ranges(conditions)
    designs = [d for d in default_design_table.designs if tuple(d.labels) in ranges]
    assert len(designs) == len(ranges) == 3
    table = with_switching_certificates(dataclasses.replace(
        default_design_table, designs=designs, conditions=conditions, switching=None))
    cut = dataclasses.replace(table, designs=[d for d in designs if d.labels != ["snow"]])
    return (yaml.safe_dump(dataclasses.asdict(conditions)), dump_design_table(table),
            dump_design_table(cut))


def _project(where: Path, argv: list[str], conditions: str, designs: str) -> None:
    """The files a command names, at those paths under ``where``: the shipped vehicle and
    settings, the example's conditions and a design table."""
    paths = _paths(argv)
    for name, text in (("vehicle", default_path("vehicle.yaml").read_text()),
                       ("settings", default_path("settings.yaml").read_text()),
                       ("conditions", conditions), ("design", designs)):
        target = where / paths[name]
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_text(text)


def test_the_workflow_and_the_hook_run_one_verify_command_on_the_files_the_hook_watches():
    commands = workflow_commands()
    assert len(commands) == 1
    assert commands[0][:2] == ["drake-cert", "verify"] and "--complete" in commands[0]
    assert sorted(commands[0]) == sorted(hook_command())
    watched = re.compile(hook()["files"])
    for path in _paths(commands[0]).values():
        assert watched.search(path), path
    install = [s["run"] for s in yaml.safe_load((CI / "verify-designs.yml").read_text())[
        "jobs"]["verify"]["steps"] if "pip install" in s.get("run", "")]
    assert len(install) == 1 and install[0].split()[-1] == "."  # this repository


def test_the_example_commands_pass_a_complete_table_and_fail_one_without_snow(
        example, tmp_path, monkeypatch, capsys):
    conditions, complete, cut = example
    monkeypatch.chdir(tmp_path)
    commands = {tuple(argv) for argv in [*workflow_commands(), hook_command()]}
    for argv in map(list, commands):  # each distinct command once (they are the same now)
        _project(tmp_path, argv, conditions, complete)
        assert cli.main(argv[1:]) == 0
        assert "3 claims hold: 3 safe speeds, 0 ranges certified to have none; complete" in \
            capsys.readouterr().err
        _project(tmp_path, argv, conditions, cut)
        assert cli.main(argv[1:]) == 1
        assert ("incomplete table: no design for label range snow (preset rain-to-snow)"
                in capsys.readouterr().err)


def test_the_hook_script_execs_drake_cert_with_its_arguments(tmp_path):
    """With its environment already made (a stand-in that runs this interpreter's drake-cert),
    the script installs nothing and hands its arguments over."""
    script = CI / "pre-commit-hook.sh"
    assert os.access(script, os.X_OK)
    if shutil.which("git") is None:
        pytest.skip("the hook script finds the repository with git")
    venv = tmp_path / "venv"
    (venv / "bin").mkdir(parents=True)
    stand_in = venv / "bin" / "drake-cert"
    stand_in.write_text(f'#!/bin/sh\nexec "{sys.executable}" -m drake_cert.cli "$@"\n')
    stand_in.chmod(0o755)
    (venv / ".installed").touch()
    env = {**os.environ, "DRAKE_CERT_HOOK_VENV": str(venv), "PYTHON": "/nonexistent/python"}
    out = subprocess.run([str(script), "--version"], capture_output=True, text=True, cwd=ROOT,
                         env=env, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("drake-cert ") and "installing" not in out.stderr
