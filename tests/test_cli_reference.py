"""docs/reference/commands.md is what the command's parsers declare: regenerated here and compared,
so an option added, removed or changed without the page fails (run ``python -m benchmarks.cli_reference``)."""

from __future__ import annotations

from benchmarks.cli_reference import PAGE, command_parser, render
from twinfocus.cli import COMMANDS


def test_the_committed_reference_matches_the_parsers() -> None:
    assert PAGE.read_text(encoding="utf-8") == render(), "stale: run python -m benchmarks.cli_reference"


def test_every_command_and_option_is_on_the_page() -> None:
    text = render()
    for name in COMMANDS:
        assert f"## `twinfocus {name}`" in text
        for action in command_parser(name)._actions:
            if action.dest == "help":
                continue
            for flag in action.option_strings:
                assert f"`{flag}`" in text, f"twinfocus {name} {flag}"


def test_a_new_option_makes_the_page_stale(monkeypatch) -> None:
    import twinfocus.cli.convert as convert

    add = convert.add_arguments

    def with_one_more(parser):
        add(parser)
        parser.add_argument("--a-new-option", help="something new")

    monkeypatch.setattr(convert, "add_arguments", with_one_more)
    assert "`--a-new-option`" in render() != PAGE.read_text(encoding="utf-8")
