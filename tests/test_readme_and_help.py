"""README and ``feedbench --help`` agree with what the commands do (issue 25.7): every
sub-command is named in ``--help`` and in the README's command table, the README gives the
demo's run count as the demo makes it and its time once."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pytest

from feedbench.commands.cli import build_parser, main
from feedbench.config import OWN_DISTRIBUTION
from feedbench.engine.family import examples

README = (Path(__file__).parents[1] / "README.md").read_text(encoding="utf-8")

NUMBER_WORDS = ("zero", "one", "two", "three", "four", "five", "six", "seven", "eight",
                "nine", "ten", "eleven", "twelve")


DURATION = re.compile(r"\b\d+(\.\d+)?(–\d+(\.\d+)?)? ?(s|min)\b(?! of bench time)")
"""A wall-clock duration in the README's prose (not a run's length in bench time)."""


def subcommands() -> list[str]:
    """The sub-commands `build_parser` registers, in order."""
    actions = build_parser()._subparsers._group_actions
    return [name for action in actions if isinstance(action, argparse._SubParsersAction)
            for name in action.choices]


def section(title: str) -> str:
    """The README's text under the ``## title`` heading, up to the next heading."""
    match = re.search(rf"^## {re.escape(title)}\n(.*?)(?=^#)", README, re.S | re.M)
    assert match, title
    return match.group(1)


def test_help_names_every_subcommand(capsys):
    """``feedbench --help`` lists every sub-command with its help line and names them all in
    its description (issue 25: tune and catalog were missing from it)."""
    with pytest.raises(SystemExit) as done:
        main(["--help"])
    assert done.value.code == 0
    text = capsys.readouterr().out
    names = subcommands()
    assert {"tune", "catalog", "run", "demo"} <= set(names) and len(names) >= 12
    description = re.search(r"The feedbench command: ([^.]*)\.", text.replace("\n", " "))
    assert description and re.split(r",\s+", description.group(1)) == names
    for name in names:
        assert re.search(rf"^    {name} +\S", text, re.M), name


def test_readme_command_table_names_every_subcommand():
    """Every sub-command has a row in the README's command table (and no row names one that
    does not exist)."""
    rows = re.findall(r"^\| `feedbench (\w+)", section("Commands"), re.M)
    assert sorted(set(rows)) == sorted(subcommands())


def test_readme_gives_the_demos_run_count_and_its_time_once():
    """The demo section says how many runs the demo makes (feedbench's own examples: 10; it said
    nine), and the quick demo's time stands in one place only (it was given as ≈ 2 min,
    ≈ 2.5–3 min and 98 s)."""
    demo = section("The demo")
    assert re.search(rf"\b{NUMBER_WORDS[len(examples(OWN_DISTRIBUTION))]}\s+runs\b", demo)
    text = " ".join(README.split())
    sentences = re.split(r"(?<=[.:;])\s+(?=[A-Z`(-])", text)
    timed = [s for s in sentences if "demo" in s and DURATION.search(s)]
    assert len(timed) == 1 and "--quick" in timed[0], timed
