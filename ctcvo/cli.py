"""``ctcvo``: the one console command; each stage's verbs are its sub-commands.

The stage's own parser does the work: this module only picks it, so ``ctcvo teacher -h``
is that stage's help, and importing a stage waits until it is named.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Sequence

from ctcvo import __version__

#: sub-command -> (module with ``main(argv)``, one line of help)
STAGES = {
    "teacher": ("ctcvo.teacher.cli", "classical RGB-D odometry: relative-pose labels with covariances (generate)"),
    "learner": ("ctcvo.learner.cli", "the CNN + LSTM trained on teacher labels (fit, calibrate, predict)"),
    "posegraph": ("ctcvo.posegraph.cli", "GTSAM fusion of teacher and learner edges, and the error report "
                                         "(optimize, calibrate)"),
    "online": ("ctcvo.pipeline.online_cli", "frame-by-frame odometry of a recording or a folder being written"),
    "demo": ("ctcvo.pipeline.demo", "every stage end to end on the built-in synthetic rooms"),
}


def usage() -> str:
    width = max(map(len, STAGES))
    lines = ["usage: ctcvo [-h] [--version] STAGE ...", "",
             "Self-supervised RGB-D visual odometry (CTCNet): teacher labels -> learner -> pose graph.", "",
             "stages:"]
    lines += [f"  {name:<{width}}  {text}" for name, (_, text) in STAGES.items()]
    lines += ["", "`ctcvo STAGE -h` shows a stage's own options; `python -m ctcvo ...` works the same."]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] in ("-h", "--help"):
        print(usage(), file=sys.stdout if args else sys.stderr)
        return 0 if args else 2
    if args[0] == "--version":
        print(f"ctcvo {__version__}")
        return 0
    if args[0] not in STAGES:
        print(f"ctcvo: error: unknown stage {args[0]!r} (choose from {', '.join(STAGES)})", file=sys.stderr)
        return 2
    module = importlib.import_module(STAGES[args[0]][0])  # lazy: a stage's imports only when named
    return module.main(args[1:])


if __name__ == "__main__":
    sys.exit(main())
