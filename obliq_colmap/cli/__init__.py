"""Command line: ``obliq-colmap SUBCOMMAND [options]``.

Each subcommand lives in its own module of this package with two functions,
``add_arguments(parser)`` and ``run(args) -> int``; they parse options, build
the options dataclasses and call one package function. No maths here.
Logging is configured only in :func:`main`.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager

from obliq_colmap import __version__
from obliq_colmap.errors import InputError

#: subcommand -> (module under obliq_colmap.cli, one-line help)
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "synth": ("synth", "generate a synthetic oblique city with ground truth"),
    "evaluate": ("evaluate", "measure a result model against ground truth"),
    "vanishing": ("vanishing", "detect vertical vanishing points in images"),
    "register": ("register", "register oblique images to a cadastral map"),
    "export": ("export", "write a result model as absolute, OPK or text"),
    "report": ("report", "write an HTML report of a registration"),
    "georegister": (
        "georegister",
        "bring an existing COLMAP SfM model onto the map (control points)",
    ),
    "export_products": (
        "export_products",
        "terrain grid, building heights, LoD1 model, map discrepancies",
    ),
    "export_dense": ("export_dense", "write a COLMAP dense-matching workspace"),
}

logger = logging.getLogger("obliq_colmap")


def bool01(text: str) -> bool:
    """An argparse type: a 0 / 1 flag, as COLMAP writes booleans."""
    if text not in ("0", "1"):
        raise argparse.ArgumentTypeError(f"expected 0 or 1, got {text!r}")
    return text == "1"


def _available_subcommands() -> dict[str, object]:
    modules = {}
    for name, (module, _) in SUBCOMMANDS.items():
        try:
            modules[name] = importlib.import_module(f"obliq_colmap.cli.{module}")
        except ModuleNotFoundError as exc:  # a stage not built yet
            if exc.name != f"obliq_colmap.cli.{module}":
                raise
    return modules


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="obliq-colmap",
        description="Register oblique aerial images to a cadastral map; "
        "read and write COLMAP models.",
    )
    parser.add_argument("--version", action="version", version=__version__)
    parser.add_argument(
        "--log_level",
        default="INFO",
        choices=["DEBUG", "INFO", "WARNING", "ERROR"],
        help="logging verbosity (default INFO)",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, module in _available_subcommands().items():
        p = sub.add_parser(name, help=SUBCOMMANDS[name][1])
        module.add_arguments(p)
        p.set_defaults(_run=module.run)
    return parser


class Terminated(KeyboardInterrupt):
    """SIGTERM (``kill``, ``timeout``, a batch scheduler's limit), raised in
    the main thread so that the run unwinds as after Ctrl-C: the workers
    shut down, nothing half-written left behind."""


def _raise_terminated(signum, frame) -> None:
    raise Terminated


@contextmanager
def _sigterm_unwinds() -> Iterator[None]:
    """SIGTERM raises :class:`Terminated` while the command runs (in the
    main thread only: signals reach no other), the previous handler after."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``obliq-colmap`` console script."""
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=getattr(logging, args.log_level),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        datefmt="%H:%M:%S",
    )
    try:
        with _sigterm_unwinds():
            return int(args._run(args) or 0)
    except InputError as exc:
        print(f"obliq-colmap {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except Terminated:
        print("terminated", file=sys.stderr)
        return 143
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
