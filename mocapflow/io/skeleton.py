"""SKELETON.json: the skeleton model (``mocapflow.mocap.model.SkeletonModel``) as a file."""

from __future__ import annotations

from pathlib import Path

from pydantic import ValidationError

from mocapflow.errors import MocapFileError
from mocapflow.mocap.model import SkeletonModel


def read_skeleton(path: str | Path) -> SkeletonModel:
    """A skeleton written by ``mocapflow calibrate``; a one-line MocapFileError when it is missing or malformed."""
    path = Path(path)
    try:
        return SkeletonModel.model_validate_json(path.read_bytes())
    except FileNotFoundError:
        raise MocapFileError(f"{path}: no such file") from None
    except OSError as exc:
        raise MocapFileError(f"{path}: cannot read: {exc.strerror}") from None
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(map(str, first["loc"])) or "file"
        raise MocapFileError(f"{path}: not a skeleton file ({where}: {first['msg']})") from None


def write_skeleton(path: str | Path, skeleton: SkeletonModel) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(skeleton.model_dump_json(indent=2) + "\n")
