"""The ``twinfocus`` command: one sub-command per module in this package.

Each sub-command module defines ``add_arguments(parser)`` and ``run(args) -> int``. Modules
are imported only when their command runs, so ``twinfocus --help`` stays fast and a missing
optional dependency of one command never breaks another.
"""

from __future__ import annotations

import argparse
import importlib
import sys
import warnings

from twinfocus.errors import TwinFocusError

# command name -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "simulate": ("twinfocus.cli.simulate", "simulate a handheld scan (and a motion-stage template scan)"),
    "focus": ("twinfocus.cli.focus", "focus a scan file offline with a twin reference"),
    "batch": ("twinfocus.cli.batch", "focus every scan of a manifest on Dask (local cluster or --scheduler)"),
    "twin": ("twinfocus.cli.twin", "digital twin: stereo pair + seed -> reference point cloud and template"),
    "rig": ("twinfocus.cli.rig", "measure the camera's offset from the radar once (a rig file for --rig)"),
    "render": ("twinfocus.cli.render", "render the simulated scene as the stereo camera sees it (left/right PNG)"),
    "launch": ("twinfocus.cli.launch", "start a graph of nodes from a launch file (launch/sim.yaml, ...)"),
    "record": ("twinfocus.cli.record", "record topics of a running graph to an MCAP log"),
    "play": ("twinfocus.cli.play", "replay an MCAP log onto a running graph"),
    "export": (
        "twinfocus.cli.export",
        "export an MCAP log for another viewer (--to foxglove: Foxglove's well-known schemas)",
    ),
    "topic": ("twinfocus.cli.topic", "list, echo or measure the rate of topics of a running graph"),
    "convert": (
        "twinfocus.cli.convert",
        "convert a TI MMWCAS capture folder + trajectory file to a scan file (+ MCAP)",
    ),
    "calibrate": (
        "twinfocus.cli.calibrate",
        "a capture of one corner reflector -> the array's channel calibration (for convert --calibration)",
    ),
    "devices": ("twinfocus.cli.devices", "list attached radars, capture boards and cameras (USB)"),
    "bench": (
        "twinfocus.cli.bench",
        "reproduce the paper's evaluation in simulation: report with tables, plots, limits",
    ),
}


class _OneLineParser(argparse.ArgumentParser):
    """A command's parser: a bad option is one line (which option, what it takes) and exit 2."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} ({self.prog} --help lists the options)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="twinfocus",
        description="Twin-reference autofocus for handheld mmWave SAR imaging.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name, (module_name, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.set_defaults(_module=module_name)
        # Arguments are added lazily in main() for the chosen command only.
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    # Find the command first, then let its module declare its arguments.
    if argv and argv[0] in COMMANDS:
        module = importlib.import_module(COMMANDS[argv[0]][0])
        sub_parser = _OneLineParser(prog=f"twinfocus {argv[0]}", description=COMMANDS[argv[0]][1])
        module.add_arguments(sub_parser)
        args = sub_parser.parse_args(argv[1:])
        with warnings.catch_warnings():
            warnings.showwarning = _one_line_warning(argv[0], warnings.showwarning)
            return _run(argv[0], module, args)
    parser.parse_args(argv)  # prints usage / unknown-command error and exits
    return 2


def _one_line_warning(command: str, show_others):
    """``warnings.showwarning`` for a command: the library's own warnings (a cloud's dropped rows,
    say) as one line in the user's terms, without the source line Python adds; others as usual."""

    def show(message, category, filename, lineno, file=None, line=None):
        if issubclass(category, UserWarning) and category.__module__.startswith("twinfocus"):
            print(f"twinfocus {command}: warning: {message}", file=sys.stderr)
        else:
            show_others(message, category, filename, lineno, file, line)

    return show


def _run(command: str, module, args: argparse.Namespace) -> int:
    """Run a parsed command: a user's mistake or a full disk is one line and exit status 2."""
    try:
        return int(module.run(args) or 0)
    except TwinFocusError as exc:
        print(f"twinfocus {command}: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        # a full disk (any writer) is the user's to fix: one line naming the file
        from twinfocus.io.atomic import disk_error_message  # lazy: numpy (+0.98 s on twinfocus --help)

        line = disk_error_message(exc)
        if line is None:
            raise
        print(f"twinfocus {command}: error: {line}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"twinfocus {command}: interrupted", file=sys.stderr)
        return 130
    finally:
        # a background import still running would tear down mid-import at exit (a traceback
        # after the refusal's line): let it finish first
        settings = sys.modules.get("twinfocus.focus.settings")  # only a command that imported it preloads
        if settings is not None:
            settings.wait_for_preload()


if __name__ == "__main__":
    sys.exit(main())
