"""What the three command-line tools (``teacher``, ``learner``, ``posegraph``) share.

* :func:`make_parser` / :func:`add_command`: one help layout (every option's default is
  shown after its help text) and one ``-v/--verbose`` accepted before or after the command;
* :func:`run`: logging set-up and the mapping of known failures to one line on stderr
  (:class:`~data.errors.VOError` -> ``error: ...``, exit 1; Ctrl-C -> exit 130).
"""

from __future__ import annotations

import argparse
import sys
import textwrap
from collections.abc import Callable

from ctcvo.data.errors import VOError, one_line
from ctcvo.data.io import setup_logging


class HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """Descriptions as written; ``(default: X)`` after an option's help unless it has no
    default value (None, a flag's False) or the help already says it."""

    def _get_help_string(self, action: argparse.Action) -> str:
        h = action.help or ""
        if "%(default)" in h or "default" in h or action.default is None or action.default is False \
                or action.default is argparse.SUPPRESS \
                or isinstance(action, (argparse._HelpAction, argparse._VersionAction)):
            return h
        if isinstance(action, argparse._StoreFalseAction):
            return h
        return h + " (default: %(default)s)"


def _fill(text: str) -> str:
    """Paragraphs (separated by blank lines, or one per line) wrapped at 79 columns."""
    return "\n\n".join("\n".join(textwrap.fill(line, 79) for line in para.splitlines())
                       for para in text.split("\n\n"))


def _verbose(p: argparse.ArgumentParser, default: object) -> None:
    p.add_argument("-v", "--verbose", action="store_true", default=default,
                   help="debug messages of this project's modules")


def make_parser(prog: str, description: str) -> tuple[argparse.ArgumentParser, argparse._SubParsersAction]:
    """The top-level parser with ``-v`` and its sub-command list."""
    p = argparse.ArgumentParser(prog=prog, description=_fill(description), formatter_class=HelpFormatter)
    _verbose(p, False)
    return p, p.add_subparsers(dest="command", required=True, metavar="COMMAND")


def add_command(sub: argparse._SubParsersAction, name: str, help: str,
                description: str = "") -> argparse.ArgumentParser:
    """A sub-command (which also takes ``-v``, after the command name)."""
    c = sub.add_parser(name, help=help, description=_fill(description or help), formatter_class=HelpFormatter)
    _verbose(c, argparse.SUPPRESS)  # absent unless given here: the top-level value stays
    return c


def run(args: argparse.Namespace, body: Callable[[argparse.Namespace], int | None],
        interrupted: str = "interrupted (finished work is kept; rerun to continue)",
        fmt: str = "%(levelname)s %(name)s: %(message)s") -> int:
    """Set up logging, call ``body(args)``; one line on stderr for known failures."""
    setup_logging(args.verbose, fmt)
    try:
        return body(args) or 0
    except VOError as exc:
        print(f"error: {one_line(exc)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"error: {interrupted}", file=sys.stderr)
        return 130
