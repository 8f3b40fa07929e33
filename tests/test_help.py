"""Every command's --help is a user's text: every option shows its default, no Sphinx
roles or maintainer notes, and no claim the options contradict."""

from __future__ import annotations

import argparse
import importlib
import re

import pytest

PARSERS = {"online": ("ctcvo.pipeline.online_cli", "build_parser"), "teacher": ("ctcvo.teacher.cli", "build_parser"),
           "learner": ("ctcvo.learner.cli", "_parser"), "posegraph": ("ctcvo.posegraph.cli", "_parser")}


def _commands() -> list[tuple[str, argparse.ArgumentParser]]:
    def walk(p: argparse.ArgumentParser, name: str):
        yield name, p
        for a in p._actions:
            if isinstance(a, argparse._SubParsersAction):
                for n, sp in a.choices.items():
                    yield from walk(sp, f"{name} {n}")

    out = []
    for stage, (module, fn) in PARSERS.items():
        out += list(walk(getattr(importlib.import_module(module), fn)(), stage))
    return out


@pytest.mark.parametrize(("name", "parser"), _commands(), ids=lambda v: v if isinstance(v, str) else "")
def test_help_shows_every_default_and_no_internals(name, parser) -> None:
    text = parser.format_help()
    assert not re.search(r":(func|class|mod|data|meth|attr):|``|\bissue \d+|\bcommit [0-9a-f]{7}", text), name
    flat = " ".join(text.split())
    for a in parser._actions:
        if not a.option_strings or a.required or isinstance(a, (argparse._HelpAction, argparse._VersionAction,
                                                                  argparse._StoreTrueAction,
                                                                  argparse._StoreFalseAction)):
            continue
        shown = " ".join(parser.formatter_class(prog=name)._get_help_string(a).split())
        if "%(default)s" in shown:
            shown = shown.replace("%(default)s", str(a.default))
        assert "default" in shown or "required" in shown, (name, a.option_strings)
        assert shown.split("(default")[0].strip()[:30] in flat  # what is checked is what --help prints


def test_help_of_zero_defaults_and_calibrate() -> None:
    helps = dict(_commands())
    assert "(default: 0)" in " ".join(helps["teacher vocabulary"].format_help().split())
    pg = helps["posegraph"].format_help()
    assert "no ground truth" not in pg.split("calibrate", 1)[1].split("\n")[0]  # it offers --method groundtruth
    online = " ".join(helps["online"].format_help().split())
    from ctcvo.pipeline.online_loop import OnlineConfig

    device = online.rsplit("--device", 1)[1].split(" --")[0]
    assert "(default: auto)" in device
    assert f"(default: {OnlineConfig.timeout_s})" in online.rsplit("--timeout TIMEOUT", 1)[1][:120]
