"""Errors the command-line tools turn into a one-line message and exit code 1."""

from __future__ import annotations


class VOError(Exception):
    """Base class for expected, user-facing failures (bad input, missing files...).

    The CLIs catch it, print ``error: <message>`` on one line and exit non-zero.
    """


def one_line(exc: BaseException) -> str:
    """``exc``'s message on one line (a wrapped library message may span several)."""
    return " ".join(str(exc).split())


class DataError(VOError):
    """A dataset file or folder is missing, corrupt or malformed."""


class FormatError(VOError):
    """A project file (TUM, g2o, CSV, JSON) does not follow docs/formats.md."""


class ConfigError(VOError):
    """Command-line arguments or a configuration are inconsistent."""


class MissingInputError(DataError):
    """What an earlier stage writes is missing; the message names the command that writes it."""
