"""Write docs/reference/commands.md and a page per command from the ``twinfocus`` command's own parsers.

    python -m benchmarks.cli_reference                 # rewrite docs/reference/commands.md and commands/
    python -m benchmarks.cli_reference --check         # exit 1 when a committed page is stale

The pages are made from what each sub-command's ``add_arguments`` declares (options, choices,
defaults, help), so they say what the code accepts; ``tests/test_cli_reference.py`` fails when
a committed page differs from a fresh one. commands.md lists the commands; each has its own page
(docs/reference/commands/NAME.md), so no page grows past what a reader finishes.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from pathlib import Path

from twinfocus.cli import COMMANDS

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "reference" / "commands.md"
COMMAND_PAGES = PAGE.with_suffix("")
WIDTH = 100

HEADER = """# Reference: commands and options

Every `twinfocus` command and each of its options, as the command itself declares them
(`twinfocus COMMAND --help` prints the same). This page is generated: after changing a
command's options, run `python -m benchmarks.cli_reference`.

Common to all commands: a mistake in what you type (an unknown option, a missing file, a bad
value) ends with one line naming it and exit status 2; results are written through temporary
files, so a failed run leaves earlier results as they were.

"""


def command_parser(name: str) -> argparse.ArgumentParser:
    """The parser ``twinfocus NAME`` uses (as :func:`twinfocus.cli.main` builds it)."""
    module_name, help_text = COMMANDS[name]
    parser = argparse.ArgumentParser(prog=f"twinfocus {name}", description=help_text)
    importlib.import_module(module_name).add_arguments(parser)
    return parser


def _usage(parser: argparse.ArgumentParser) -> str:
    fmt = argparse.HelpFormatter(parser.prog, width=WIDTH)
    fmt.add_usage(parser.usage, parser._actions, parser._mutually_exclusive_groups)
    return fmt.format_help().strip()


def _cell(text: str) -> str:
    return " ".join(text.split()).replace("|", "\\|")


def _option_rows(parser: argparse.ArgumentParser) -> list[str]:
    fmt = argparse.HelpFormatter(parser.prog, width=WIDTH)
    rows = []
    for action in parser._actions:
        if isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)):
            continue
        name = ", ".join(f"`{s}`" for s in action.option_strings) or f"`{action.dest}`"
        if action.choices is not None:
            value = " \\| ".join(f"`{c}`" for c in action.choices)
        elif action.nargs == 0:
            value = ""
        else:
            metavar = action.metavar if action.metavar is not None else action.dest.upper()
            value = f"`{' '.join(metavar) if isinstance(metavar, tuple) else metavar}`"
            if action.nargs in ("+", "*"):
                value += " ..."
        default = (
            "" if action.default in (None, False, argparse.SUPPRESS) or action.nargs == 0 else f"`{action.default}`"
        )
        help_text = fmt._expand_help(action) if action.help not in (None, argparse.SUPPRESS) else ""
        required = " (required)" if action.required and action.option_strings else ""
        rows.append(f"| {name}{required} | {value} | {default} | {_cell(help_text)} |")
    return rows


def _section(parser: argparse.ArgumentParser, level: int) -> list[str]:
    lines = [f"{'#' * level} `{parser.prog}`", ""]
    if parser.description:
        lines += [_cell(parser.description), ""]
    lines += ["```", _usage(parser), "```", ""]
    rows = _option_rows(parser)
    if rows:
        lines += ["| option | value | default | what it does |", "|---|---|---|---|", *rows, ""]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in dict.fromkeys(action.choices.values()):
                lines += _section(sub, level + 1)
    return lines


def render() -> str:
    """The index page, as text: every command with a link to its own page."""
    lines = [HEADER.rstrip(), "", "| command | what it does |", "|---|---|"]
    lines += [
        f"| [`twinfocus {name}`]({COMMAND_PAGES.name}/{name}.md) | {_cell(text)} |"
        for name, (_, text) in COMMANDS.items()
    ]
    return "\n".join(lines).rstrip() + "\n"


def render_command(name: str) -> str:
    """One command's page, as text."""
    lines = [*_section(command_parser(name), 1), f"All commands: [commands](../{PAGE.name}).", ""]
    return "\n".join(lines).rstrip() + "\n"


def render_pages() -> dict[Path, str]:
    """Every page this script writes: the index and one per command."""
    pages = {PAGE: render()}
    pages.update({COMMAND_PAGES / f"{name}.md": render_command(name) for name in COMMANDS})
    return pages


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.cli_reference", description=__doc__.split("\n")[0])
    p.add_argument("--check", action="store_true", help="only compare; exit 1 when a page differs")
    args = p.parse_args(argv)
    pages = render_pages()
    stale = sorted(
        str(path.relative_to(ROOT))
        for path in {*pages, *COMMAND_PAGES.glob("*.md")}
        if not path.is_file() or path.read_text(encoding="utf-8") != pages.get(path)
    )
    if args.check:
        print(f"stale: {', '.join(stale)}; run python -m benchmarks.cli_reference" if stale else "up to date")
        return 1 if stale else 0
    COMMAND_PAGES.mkdir(parents=True, exist_ok=True)
    for path in COMMAND_PAGES.glob("*.md"):
        if path not in pages:
            path.unlink()  # a command that no longer exists
    for path, text in pages.items():
        path.write_text(text, encoding="utf-8")
    print(f"wrote {PAGE.relative_to(ROOT)} and {len(pages) - 1} command pages in {COMMAND_PAGES.relative_to(ROOT)}/")
    return 0


if __name__ == "__main__":
    sys.exit(main())
