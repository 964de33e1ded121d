"""Biovision Hierarchy (BVH) skeletal animation: a joint tree with per-frame local rotations and translations.

The ``Bvh`` object keeps everything a writer needs to reproduce the file's layout: joint order, offsets, each joint's
channel list (which fixes its Euler order) and end sites. Rotations are stored as matrices: Euler channels applied
in the order listed, i.e. ``R = R_c1 @ R_c2 @ R_c3`` (intrinsic), as in every BVH exporter.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from mocapflow.errors import MocapFileError

_POSITION = ("xposition", "yposition", "zposition")
_ROTATION = ("xrotation", "yrotation", "zrotation")


@dataclass
class Bvh:
    """A BVH skeleton and its motion, in the file's units and axes (usually y up)."""

    names: list[str]  # J joints, parents first (file order)
    parents: np.ndarray  # (J,) parent index, -1 for the root
    offsets: np.ndarray  # (J, 3) joint origin in its parent's frame at rest
    channels: list[tuple[str, ...]]  # per joint, as in the file, e.g. ("Xposition", ..., "Zrotation")
    end_sites: dict[int, np.ndarray]  # joint index -> offset of its End Site
    frame_time: float  # s
    translations: np.ndarray  # (F, J, 3) local translation: the offset, or the position channels where present
    rotations: np.ndarray  # (F, J, 3, 3) local rotations (identity for joints without rotation channels)

    @property
    def frames(self) -> int:
        return len(self.rotations)

    @property
    def rate(self) -> float:
        return 1.0 / self.frame_time

    @property
    def root_translation(self) -> np.ndarray:
        """(F, 3) root position per frame."""
        return self.translations[:, 0]

    def index(self, name: str) -> int:
        """Index of a joint by name, ignoring case."""
        lowered = [n.lower() for n in self.names]
        try:
            return lowered.index(name.lower())
        except ValueError:
            raise KeyError(name) from None

    def local_rotations(self, joint: int) -> Rotation:
        """The (F,) local rotations of one joint as a scipy Rotation."""
        return Rotation.from_matrix(self.rotations[:, joint])

    def world_transforms(self) -> tuple[np.ndarray, np.ndarray]:
        """World rotations (F, J, 3, 3) and positions (F, J, 3) of every joint."""
        rot = np.empty_like(self.rotations)
        pos = np.empty_like(self.translations)
        for j, p in enumerate(self.parents):
            if p < 0:
                rot[:, j], pos[:, j] = self.rotations[:, j], self.translations[:, j]
            else:
                rot[:, j] = rot[:, p] @ self.rotations[:, j]
                pos[:, j] = np.einsum("fij,fj->fi", rot[:, p], self.translations[:, j]) + pos[:, p]
        return rot, pos

    def forward_kinematics(self) -> np.ndarray:
        """(F, J, 3) world positions of the joints."""
        return self.world_transforms()[1]


class _Tokens:
    """Whitespace tokens of the hierarchy with the error reporting of the file they come from."""

    def __init__(self, path: Path, words: list[str]) -> None:
        self.path, self.words, self.pos = path, words, 0

    def next(self, what: str) -> str:
        if self.pos >= len(self.words):
            raise MocapFileError(f"{self.path}: not a valid BVH file (ends where {what} was expected)")
        self.pos += 1
        return self.words[self.pos - 1]

    def expect(self, word: str) -> None:
        got = self.next(repr(word))
        if got.lower() != word.lower():
            raise MocapFileError(f"{self.path}: not a valid BVH file (expected {word!r}, found {got!r})")

    def number(self, what: str) -> float:
        got = self.next(what)
        try:
            return float(got)
        except ValueError:
            raise MocapFileError(f"{self.path}: not a valid BVH file ({what} is {got!r}, not a number)") from None


def read_bvh(path: str | Path) -> Bvh:
    """Read a BVH file; raise MocapFileError with a one-line reason when it is missing or malformed."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except FileNotFoundError:
        raise MocapFileError(f"{path}: no such file") from None
    except OSError as exc:
        raise MocapFileError(f"{path}: cannot read ({exc.strerror})") from None
    head, sep, motion = text.partition("MOTION")
    if not sep or not head.lstrip().upper().startswith("HIERARCHY"):
        raise MocapFileError(f"{path}: not a BVH file (no HIERARCHY and MOTION sections)")
    names, parents, offsets, channels, end_sites = _hierarchy(_Tokens(path, head.split()[1:]))
    tok = _Tokens(path, motion.split())
    tok.expect("Frames:")
    frames = tok.number("the frame count")
    tok.expect("Frame")
    tok.expect("Time:")
    frame_time = tok.number("the frame time")
    if frames != int(frames) or frames < 1 or not frame_time > 0:
        raise MocapFileError(f"{path}: not a valid BVH file (Frames: {frames:g}, Frame Time: {frame_time:g})")
    frames = int(frames)
    width = sum(len(c) for c in channels)
    try:
        values = np.array(tok.words[tok.pos:], dtype=float)
    except ValueError:
        raise MocapFileError(f"{path}: not a valid BVH file (non-numeric motion data)") from None
    if values.size != frames * width:
        raise MocapFileError(
            f"{path}: truncated or malformed BVH motion ({values.size} values for {frames} frames x {width} channels)"
        )
    translations, rotations = _motion(values.reshape(frames, width), offsets, channels)
    return Bvh(names=names, parents=np.array(parents), offsets=offsets, channels=channels, end_sites=end_sites,
               frame_time=frame_time, translations=translations, rotations=rotations)


def _hierarchy(tok: _Tokens) -> tuple[list[str], list[int], np.ndarray, list[tuple[str, ...]], dict[int, np.ndarray]]:
    names: list[str] = []
    parents: list[int] = []
    offsets: list[list[float]] = []
    channels: list[tuple[str, ...]] = []
    end_sites: dict[int, np.ndarray] = {}
    stack: list[int] = []  # open joints; -2 marks an open End Site
    tok.expect("ROOT")
    keyword = "ROOT"
    while True:
        if keyword.upper() in ("ROOT", "JOINT"):
            if keyword.upper() == "ROOT" and names:
                raise MocapFileError(f"{tok.path}: BVH files with several roots are not supported")
            names.append(tok.next("a joint name"))
            parents.append(stack[-1] if stack else -1)
            tok.expect("{")
            tok.expect("OFFSET")
            offsets.append([tok.number("an offset") for _ in range(3)])
            tok.expect("CHANNELS")
            count = tok.number("a channel count")
            chans = tuple(tok.next("a channel name") for _ in range(int(count)))
            bad = [c for c in chans if c.lower() not in _POSITION + _ROTATION]
            if bad or count != int(count):
                raise MocapFileError(f"{tok.path}: joint {names[-1]!r} has unknown channels {bad or count}")
            channels.append(chans)
            stack.append(len(names) - 1)
        elif keyword.lower() == "end":
            tok.expect("Site")
            tok.expect("{")
            tok.expect("OFFSET")
            if not stack or stack[-1] < 0:
                raise MocapFileError(f"{tok.path}: not a valid BVH file (End Site outside a joint)")
            end_sites[stack[-1]] = np.array([tok.number("an offset") for _ in range(3)])
            tok.expect("}")
        elif keyword == "}":
            if not stack:
                raise MocapFileError(f"{tok.path}: not a valid BVH file (unbalanced braces)")
            stack.pop()
            if not stack:
                break
        else:
            raise MocapFileError(f"{tok.path}: not a valid BVH file (unexpected {keyword!r} in the hierarchy)")
        keyword = tok.next("JOINT, End Site or }")
    if tok.pos != len(tok.words):
        raise MocapFileError(f"{tok.path}: not a valid BVH file (text after the hierarchy: {tok.words[tok.pos]!r})")
    return names, parents, np.array(offsets, float), channels, end_sites


def _motion(values: np.ndarray, offsets: np.ndarray, channels: list[tuple[str, ...]]) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame local translations and rotation matrices from the channel columns."""
    frames, joints = len(values), len(channels)
    translations = np.broadcast_to(offsets, (frames, joints, 3)).copy()
    rotations = np.broadcast_to(np.eye(3), (frames, joints, 3, 3)).copy()
    column = 0
    for j, chans in enumerate(channels):
        lower = [c.lower() for c in chans]
        cols = column + np.arange(len(chans))
        column += len(chans)
        pos = [(k, _POSITION.index(c)) for k, c in enumerate(lower) if c in _POSITION]
        if pos:
            for k, axis in pos:
                translations[:, j, axis] = values[:, cols[k]]
        rot = [k for k, c in enumerate(lower) if c in _ROTATION]
        if rot:
            order = "".join(lower[k][0].upper() for k in rot)
            rotations[:, j] = Rotation.from_euler(order, values[:, cols[rot]], degrees=True).as_matrix()
    return translations, rotations
