"""Subcommands of the mocapflow CLI: each module defines ``register(subparsers)``."""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from pydantic import BaseModel, ValidationError

from mocapflow.errors import MocapflowError

if TYPE_CHECKING:
    from mocapflow.io.markers import MarkerData

M = TypeVar("M", bound=BaseModel)


JOIN_TIMEOUT_S = 5.0


def timeout_option(parser: argparse.ArgumentParser) -> None:
    """``--timeout S``: how long a command waits for a router to accept its session before saying why it cannot."""
    parser.add_argument("--timeout", type=float, default=JOIN_TIMEOUT_S, metavar="S",
                        help=f"give up, saying so, when no router accepts the session within S seconds (no router "
                             f"there, a refused login) (default {JOIN_TIMEOUT_S:g})")


def marker_choice(parser: argparse.ArgumentParser, include: bool = True) -> None:
    """The ``--markers GLOB`` / ``--exclude GLOB`` options of a command that reads a marker file."""
    if include:
        parser.add_argument("--markers", dest="include", action="append", default=[], metavar="GLOB",
                            help="use only the markers whose labels match this shell-style pattern ('L*', '*HEE'); "
                                 "repeatable")
    parser.add_argument("--exclude", action="append", default=[], metavar="GLOB",
                        help="leave out the markers whose labels match this pattern (virtual points an exporter "
                             "writes as markers, such as '*HJC' or 'CentreOfMass'); repeatable")


def read_chosen(path: str, args: argparse.Namespace) -> MarkerData:
    """A marker file, restricted to the markers chosen with ``marker_choice``'s options."""
    from mocapflow.io.markers import read_markers, select_markers

    data = read_markers(path)
    leave_out_absurd(data, path)
    include, exclude = getattr(args, "include", []), args.exclude
    if not (include or exclude):
        return data
    chosen = select_markers(data, include, exclude)
    print(f"{path}: using {chosen.n_markers} of {data.n_markers} markers")
    return chosen


def leave_out_absurd(data: MarkerData, path: str | Path) -> None:
    """What no motion capture produces, as the live graph treats it (``runtime.integrity``): a rate over 100 kHz is
    refused; samples over 100 m from the origin are left out as missing, said in one line, and a file with no other
    sample is refused."""
    import numpy as np

    from mocapflow.io.markerdata import FLAG_MISSING
    from mocapflow.runtime.integrity import MAX_COORDINATE_MM, MAX_RATE_HZ, beyond_volume

    if data.rate > MAX_RATE_HZ:
        raise MocapflowError(f"{path}: a rate of {data.rate:g} Hz is beyond any tracker ({MAX_RATE_HZ:,} Hz at most)")
    beyond = beyond_volume(data.positions)
    if not beyond.any():
        return
    f, m = np.argwhere(beyond)[0]
    what = (f"beyond {MAX_COORDINATE_MM / 1000:g} m from the origin (first: {data.labels[m]} at frame "
            f"{data.first_frame + f}, {data.positions[f, m].tolist()} mm)")
    if not (np.isfinite(data.positions).all(axis=2) & ~beyond).any():
        raise MocapflowError(f"{path}: every sample lies {what}: not motion capture, or not in the unit the file "
                             "states")
    data.positions[beyond] = np.nan
    if data.flags is not None:
        data.flags[beyond] = FLAG_MISSING
    print(f"{path}: {int(beyond.sum())} samples {what} left out as missing")


def distinct_output(output: str | Path, *inputs: str | Path) -> Path:
    """The output path, refused before any work is done when it is one of the inputs (a command never overwrites what
    it reads) or when its folder cannot be made or written; the folder exists on return."""
    out = Path(output)
    for source in inputs:
        if source and out.resolve() == Path(source).resolve():
            raise MocapflowError(f"{out}: the output would overwrite an input; choose another path")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=out.parent):
            pass
    except OSError as exc:
        raise MocapflowError(f"{out}: cannot write there ({exc.strerror or exc})") from None
    return out


def settings(model: type[M], items: list[str], **named: Any) -> M:
    """A config model from ``--set KEY=VALUE`` options (values read as YAML, so numbers stay numbers) and named
    options (None = not given); a bad value is a one-line error naming the setting."""
    import yaml

    values: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise MocapflowError(f"--set {item!r}: expected KEY=VALUE")
        values[key.strip()] = yaml.safe_load(value)
    values.update({key: value for key, value in named.items() if value is not None})
    try:
        return model.model_validate(values)
    except ValidationError as exc:
        raise MocapflowError("; ".join(f"{'.'.join(map(str, e['loc'])) or 'settings'}: {e['msg']}"
                                       for e in exc.errors())) from None
