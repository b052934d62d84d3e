"""docs/reference/commands.md is what the command's parsers declare: regenerated here and compared,
so an option added, removed or changed without the page fails (run ``python -m benchmarks.cli_reference``)."""

from __future__ import annotations

from benchmarks.cli_reference import COMMAND_PAGES, PAGE, command_parser, render, render_command, render_pages
from twinfocus.cli import COMMANDS


def test_the_committed_reference_matches_the_parsers() -> None:
    pages = render_pages()
    for path, text in pages.items():
        assert path.is_file() and path.read_text(encoding="utf-8") == text, (
            f"{path.name} stale: run python -m benchmarks.cli_reference"
        )
    assert sorted(COMMAND_PAGES.glob("*.md")) == sorted(p for p in pages if p != PAGE), "a page for no command"


def test_every_command_and_option_is_on_the_page() -> None:
    for name in COMMANDS:
        assert f"({COMMAND_PAGES.name}/{name}.md)" in render()
        text = render_command(name)
        assert f"# `twinfocus {name}`" in text
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
    page = COMMAND_PAGES / "convert.md"
    assert "`--a-new-option`" in render_command("convert") != page.read_text(encoding="utf-8")
