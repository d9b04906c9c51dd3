"""The command line explains itself: every subcommand and option has help text, and ``--help``
is plain text (no reStructuredText markup, no internal issue references)."""

from __future__ import annotations

import argparse

import pytest

from acm_rs.cli import build_parser, main


def _subparsers():
    p = build_parser()
    (sub,) = [a for a in p._actions if isinstance(a, argparse._SubParsersAction)]
    helps = {c.dest: c.help for c in sub._choices_actions}
    return sub.choices, helps


def test_every_subcommand_and_option_has_help():
    choices, helps = _subparsers()
    assert {"init", "run-all", "track", "export", "view", "gapfill", "gapfill-eval"} <= set(choices)
    missing = [name for name in choices if not helps.get(name)]
    for name, sp in choices.items():
        for a in sp._actions:
            if isinstance(a, argparse._HelpAction):
                continue
            if not a.help or a.help == argparse.SUPPRESS:
                missing.append(f"{name} {'/'.join(a.option_strings) or a.dest}")
    assert not missing, f"without help text: {missing}"


@pytest.mark.parametrize("command", sorted(_subparsers()[0]))
def test_help_is_plain_text(command, capsys):
    with pytest.raises(SystemExit) as exc:
        main([command, "--help"])
    assert exc.value.code == 0
    text = capsys.readouterr().out
    assert text.startswith("usage: acm-rs " + command)
    for markup in ("``", ":func:", ":class:", ":mod:", ".. ", "issue "):
        assert markup not in text, f"{command} --help shows {markup!r}"
