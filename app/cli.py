"""The ``twohr`` command line: one module per command under :mod:`twohr_app.commands`, imported here by name.

:data:`COMMANDS` lists this package's commands in the order ``twohr --help`` shows them; each module has a
``register(subparsers)`` function. Other installed packages add commands through the ``twohr.commands``
entry-point group (:data:`COMMAND_GROUP`): that is how the lab adds its offline studies (benches, feature and
mask evaluation, matcher training) without the product naming it. Handlers import their heavy dependencies
lazily so that ``twohr --help`` stays fast.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Callable
from importlib.metadata import entry_points

from twohr.errors import TwohrError
from twohr.paths import DEV_SEQUENCE

from .commands import camera, eval, health, keys, maps, models, router, run, synth, up

Register = Callable[[argparse._SubParsersAction], None]

#: This package's commands, each under the order key that places it in ``--help`` among the entry points'.
COMMANDS: list[tuple[str, Register]] = [
    ("10-run", run.register),  # run, demo
    ("15-maps", maps.register),
    ("60-up", up.register),
    ("62-health", health.register),
    ("64-router", router.register),
    ("66-keys", keys.register),
    ("70-camera", camera.register),
    ("80-eval", eval.register),
    ("85-synth", synth.register),
    ("90-models", models.register),
]

#: The entry-point group through which installed packages add subcommands. An entry's value is a
#: ``register(subparsers)`` function (``module:register``) or a module that has one; its name is the order key,
#: sorted together with those of :data:`COMMANDS` (the lab: 20-bench, 30-features, 40-yolo, 50-matcher, 55-vocab).
COMMAND_GROUP = "twohr.commands"


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("twohr")
    except PackageNotFoundError:  # run from a source tree that was never installed
        return "unknown"


def _registrar(target) -> Register:
    """The ``register`` function itself, or the one of a module."""
    return target if callable(target) else target.register


def command_registrars() -> list[tuple[str, Register]]:
    """(order key, ``register(subparsers)``) of every command, ours and the entry points', in ``--help`` order.

    An entry point whose package is not installed (e.g. an image without the lab) is left out."""
    found = list(COMMANDS)
    for entry in entry_points(group=COMMAND_GROUP):
        try:
            found.append((entry.name, _registrar(entry.load())))
        except ModuleNotFoundError as exc:
            if exc.name is None or not (entry.module == exc.name or entry.module.startswith(exc.name + ".")):
                raise  # a dependency of an installed module is missing: a real error
    return sorted(found, key=lambda item: item[0])


def build_parser() -> argparse.ArgumentParser:
    """The whole ``twohr`` parser, every command registered."""
    parser = argparse.ArgumentParser(
        prog="twohr",
        description="2HR-Net visual SLAM for dynamic scenes: run it, evaluate it, serve it on Zenoh.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=f"Start with `twohr run --sequence {DEV_SEQUENCE}`. "
        "Every subcommand has its own --help.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for _, register in command_registrars():
        register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)  # the exact command, for the studies' stamps
    quiet = getattr(args, "quiet", False)  # --quiet: warnings and errors only
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.WARNING if quiet else logging.INFO,
                        format="%(levelname)s %(name)s: %(message)s")
    if not args.verbose:
        logging.getLogger("httpx").setLevel(logging.WARNING)  # one INFO line per request drowns the output
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except TwohrError as exc:
        print(f"twohr: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("twohr: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # e.g. `twohr eval … | head`
        sys.stderr.close()
        return 0



if __name__ == "__main__":
    sys.exit(main())
