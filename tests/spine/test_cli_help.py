"""Every subcommand's --help says what it does, what each argument is, and shows an example."""

from __future__ import annotations

import argparse

import pytest

from steerlab.app.cli import build_parser


def _subparsers() -> dict[str, argparse.ArgumentParser]:
    parser = build_parser()
    (sub,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    return dict(sub.choices)


def _one_line_help() -> dict[str, str | None]:
    parser = build_parser()
    (sub,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    return {a.dest: a.help for a in sub._choices_actions}


SUBCOMMANDS = sorted(_subparsers())


def test_every_command_is_walked():
    assert {"simulate", "export", "import", "report", "run", "rig-check", "stop", "diagnose",
            "gui"} <= set(SUBCOMMANDS)  # fmt: skip


@pytest.mark.parametrize("name", SUBCOMMANDS)
def test_help_has_a_description_argument_help_and_an_example(name):
    p = _subparsers()[name]
    assert _one_line_help()[name], f"{name}: no one-line help in `steerlab --help`"
    assert p.description and p.description.strip(), f"{name}: no description"
    assert "\n\n" not in p.description, f"{name}: the description is one paragraph"
    for action in p._actions:
        label = "/".join(action.option_strings) or action.dest
        assert action.help and action.help != argparse.SUPPRESS, f"{name} {label}: no help"
    assert p.epilog and "example" in p.epilog, f"{name}: no example in the epilog"
    assert f"steerlab {name}" in p.epilog, f"{name}: the example does not run {name}"
    # The examples keep their lines (the raw formatter), and the help renders.
    assert p.formatter_class is argparse.RawDescriptionHelpFormatter
    text = p.format_help()
    assert p.epilog.splitlines()[1] in text


def test_subjects_and_subject_say_how_they_differ():
    sim = {a.dest: a.help for a in _subparsers()["simulate"]._actions}
    run = {a.dest: a.help for a in _subparsers()["run"]._actions}
    assert "how many" in sim["subjects"] and "run --subject" in sim["subjects"]
    assert "which subject" in run["subject"] and "simulate --subjects" in run["subject"]
