"""The `matlearn` command line. Each subcommand lives in `matlearn/commands/<name>.py` and
exposes `register(subparsers)`; this module only discovers and dispatches them."""
from __future__ import annotations

import argparse
import functools
import importlib
import pkgutil
import sys
import warnings

from . import commands


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("matlearn")
    except PackageNotFoundError:
        return "(not installed)"


def _show_warning(message, category, filename, lineno, file=None, line=None):
    """Warnings on the command line as one line, without Python's source excerpt."""
    print(f"matlearn: warning: {message}", file=file or sys.stderr)


class _DefaultsFormatter(argparse.HelpFormatter):
    """Help that states every option's default (and so its unit, where the help names one)
    unless its text already does."""

    def _get_help_string(self, action):
        text = action.help or ""
        default = action.default
        if (not action.option_strings or action.required or default is None or default is False
                or default is argparse.SUPPRESS or (isinstance(default, list) and not default)
                or "default" in text.lower()):
            return text
        return f"{text} (default: %(default)s)".strip()


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="matlearn",
        description="Learn material corrections from recordings of soft objects and diagnose "
        "the sim-to-real gap. All quantities in SI units (m, s, kg, Pa).",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    sub = parser.add_subparsers(dest="command", required=True,
                                parser_class=functools.partial(argparse.ArgumentParser,
                                                               formatter_class=_DefaultsFormatter))
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda i: i.name):
        module = importlib.import_module(f"{commands.__name__}.{info.name}")
        if hasattr(module, "register"):
            module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    warnings.showwarning = _show_warning
    try:
        return int(args.func(args) or 0)
    except (OSError, ValueError, RuntimeError) as err:  # OSError: missing files, a file where a folder goes
        text = str(err) if not isinstance(err, OSError) or not err.filename else (
            f"{err.strerror or type(err).__name__}: {err.filename}")
        print(f"matlearn {args.command}: error: {text}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        hint = " (the same command with --resume continues it)" if hasattr(args, "resume") else ""
        print(f"matlearn {args.command}: interrupted{hint}", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
