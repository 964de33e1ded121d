"""mocapflow: labelled, gap-free marker streams and a live skeleton from optical motion capture.

Each subcommand lives in its own module under ``mocapflow.commands``.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import pkgutil
import sys

from mocapflow import __version__, commands
from mocapflow.errors import MocapflowError


def build_parser() -> argparse.ArgumentParser:
    """Collect every module in ``mocapflow.commands``; each adds its own subparser through ``register``."""
    parser = argparse.ArgumentParser(prog="mocapflow", description=__doc__.split("\n\n")[0])
    parser.add_argument("--version", action="version", version=f"mocapflow {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        importlib.import_module(f"mocapflow.commands.{info.name}").register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except MocapflowError as exc:
        print(f"mocapflow {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # a file the command could not read or write (permissions, a folder, a full disk)
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"mocapflow {args.command}: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # output piped into a reader that closed early (`| head`): not an error
        sys.stdout = None  # type: ignore[assignment,unused-ignore]  # nothing left to flush at exit
        return 0


if __name__ == "__main__":
    sys.exit(main())
