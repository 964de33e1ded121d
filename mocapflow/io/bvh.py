"""Biovision Hierarchy (BVH) skeletal animation: a joint tree with per-frame local rotations and translations.

The ``Bvh`` object (``mocapflow.mocap.motion``) keeps everything a writer needs to reproduce the file's layout:
joint order, offsets, each joint's channel list (which fixes its Euler order) and end sites. Rotations are stored as
matrices: Euler channels applied in the order listed, i.e. ``R = R_c1 @ R_c2 @ R_c3`` (intrinsic), as in every BVH
exporter.

``skeleton_bvh`` turns a solved skeleton (``SkeletonModel`` + ``SkeletonPose``) into a ``Bvh``: the root joint sits at
the root segment's origin (the centroid of its markers in the reference pose) with position channels; every skeleton
joint becomes a BVH joint at its centre of rotation, turning with its child segment, its OFFSET being that centre
relative to the parent BVH joint in the reference pose (where every segment frame is parallel to the world, so the
rest pose is the reference pose); a segment with no child joint ends in an End Site at its marker centroid. Axes and
units stay the data's (mm, usually z up), so forward kinematics gives back the joint centres.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial.transform import Rotation

from mocapflow.errors import MocapFileError
from mocapflow.mocap.motion import Bvh

if TYPE_CHECKING:
    from mocapflow.mocap.model import SkeletonModel
    from mocapflow.mocap.solve import SkeletonPose

_POSITION = ("xposition", "yposition", "zposition")
_ROTATION = ("xrotation", "yrotation", "zrotation")


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


def _dfs_order(parents: np.ndarray) -> list[int]:
    """Joint indices in depth-first pre-order (children in index order), the order a BVH file lists them."""
    children: dict[int, list[int]] = {}
    for j, p in enumerate(parents):
        children.setdefault(int(p), []).append(j)
    roots = children.get(-1, [])
    if len(roots) != 1:
        raise ValueError(f"a BVH skeleton has exactly one root, found {len(roots)}")
    order, stack = [], roots[:]
    while stack:
        j = stack.pop()
        order.append(j)
        stack.extend(reversed(children.get(j, [])))
    if len(order) != len(parents):
        raise ValueError("joint parents do not form a tree")
    return order


def _numbers(values: np.ndarray) -> str:
    return " ".join(f"{v:.6f}" for v in values)


def write_bvh(path: str | Path, bvh: Bvh) -> None:
    """Write ``bvh`` as a BVH file: one line per hierarchy item, one line of channel values per frame.

    Joints are written depth first, whatever order ``bvh`` keeps them in; Euler angles follow each joint's rotation
    channel order (intrinsic). Raises ValueError on non-finite motion (a BVH file has no missing values).
    """
    path = Path(path)
    for name in bvh.names:
        if not name or any(c.isspace() for c in name):
            raise ValueError(f"BVH joint names cannot be empty or hold white space: {name!r}")
    if not (np.isfinite(bvh.translations).all() and np.isfinite(bvh.rotations).all()):
        raise ValueError("BVH motion must be finite in every frame")
    order = _dfs_order(bvh.parents)
    children = {j: [c for c in order if bvh.parents[c] == j] for j in order}
    lines = ["HIERARCHY"]

    def joint(j: int, depth: int) -> None:
        pad = "\t" * depth
        lines.append(f"{pad}{'ROOT' if depth == 0 else 'JOINT'} {bvh.names[j]}")
        lines.append(f"{pad}{{")
        lines.append(f"{pad}\tOFFSET {_numbers(bvh.offsets[j])}")
        lines.append(f"{pad}\tCHANNELS {len(bvh.channels[j])} {' '.join(bvh.channels[j])}".rstrip())
        for c in children[j]:
            joint(c, depth + 1)
        if j in bvh.end_sites:
            lines.extend([f"{pad}\tEnd Site", f"{pad}\t{{", f"{pad}\t\tOFFSET {_numbers(bvh.end_sites[j])}",
                          f"{pad}\t}}"])
        lines.append(f"{pad}}}")

    joint(order[0], 0)
    columns = []
    for j in order:
        lower = [c.lower() for c in bvh.channels[j]]
        rot = [k for k, c in enumerate(lower) if c in _ROTATION]
        angles = np.zeros((bvh.frames, 0))
        if rot:
            sequence = "".join(lower[k][0].upper() for k in rot)
            angles = Rotation.from_matrix(bvh.rotations[:, j]).as_euler(sequence, degrees=True)
        for c in lower:
            if c in _POSITION:
                columns.append(bvh.translations[:, j, _POSITION.index(c)])
            else:
                columns.append(angles[:, rot.index(lower.index(c))])
    motion = np.column_stack(columns) if columns else np.zeros((bvh.frames, 0))
    lines += ["MOTION", f"Frames: {bvh.frames}", f"Frame Time: {bvh.frame_time:.8f}"]
    lines += [_numbers(row) for row in motion]
    try:
        path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    except OSError as exc:
        raise MocapFileError(f"{path}: cannot write ({exc.strerror})") from None


def _held(values: np.ndarray, known: np.ndarray, default: np.ndarray) -> np.ndarray:
    """``values`` (F, K, ...) where ``known`` (F, K) is False replaced by the last known value of that column (the
    next one before the first), or ``default`` where a column is never known."""
    frames = np.arange(len(values))[:, None]
    last = np.maximum.accumulate(np.where(known, frames, -1), axis=0)
    following = np.minimum.accumulate(np.where(known, frames, len(values))[::-1], axis=0)[::-1]
    source = np.where(last >= 0, last, np.minimum(following, len(values) - 1))
    out = np.take_along_axis(values, source.reshape(source.shape + (1,) * (values.ndim - 2)), axis=0)
    never = ~known.any(axis=0)
    out[:, never] = default
    return out


def _bvh_name(name: str) -> str:
    return "_".join(name.split()) or "joint"


def skeleton_bvh(skeleton: SkeletonModel, pose: SkeletonPose, rate: float, order: str = "ZXY") -> Bvh:
    """The solved motion of ``skeleton`` as a BVH animation (hierarchy as in the module docstring).

    ``order`` is the Euler order of every joint's rotation channels (intrinsic, e.g. "ZXY" or "XYZ"). A BVH frame
    has no missing values: where the solver could not pose a segment, its rotation relative to its parent (and the
    root's position) holds its last known value (the next known one before the first), identity if never known.
    Segments not connected to the root are left out. The BVH is rigid: a joint sits where its parent segment puts
    it, which is the solver's joint centre wherever the child segment turned about it.
    """
    if sorted(order.upper()) != ["X", "Y", "Z"]:
        raise ValueError(f"rotation order must be a permutation of XYZ, got {order!r}")
    if not rate > 0:
        raise ValueError(f"rate must be positive, got {rate}")
    index = {name: s for s, name in enumerate(pose.segment_names)}
    inner = {j.child: j for j in skeleton.joints}
    origin = {s.name: np.asarray(inner[s.name].child_offset if s.name in inner else (0.0, 0.0, 0.0), dtype=float)
              for s in skeleton.segments}
    segments: list[str] = []  # reachable from the root, depth first, so the joints come out in file order
    stack = [skeleton.root]
    while stack:
        name = stack.pop()
        if name in segments:
            raise ValueError(f"the joints of skeleton {skeleton.name!r} do not form a tree (at {name!r})")
        segments.append(name)
        stack.extend(reversed([j.child for j in skeleton.joints if j.parent == name]))
    names = [_bvh_name(skeleton.root if s == skeleton.root else inner[s].name) for s in segments]
    if len(set(names)) != len(names):
        raise ValueError(f"BVH joint names must be unique: {names}")
    node = {s: k for k, s in enumerate(segments)}
    parents = np.array([-1 if s == skeleton.root else node[inner[s].parent] for s in segments])
    offsets = np.array([np.zeros(3) if s == skeleton.root else
                        np.asarray(inner[s].parent_offset, dtype=float) - origin[inner[s].parent] for s in segments])
    has_child = {j.parent for j in skeleton.joints if j.child in node}
    end_sites = {node[s]: -origin[s] for s in segments if s not in has_child}
    columns = [index[s] for s in segments]
    local = pose.local_rotations()[:, columns]
    known = np.isfinite(local).all(-1)
    quats = _held(local, known, np.array([0.0, 0.0, 0.0, 1.0]))
    frames = len(quats)
    rotations = Rotation.from_quat(quats.reshape(-1, 4)).as_matrix().reshape(frames, len(segments), 3, 3)
    translations = np.broadcast_to(offsets, (frames, len(segments), 3)).copy()
    root = pose.translations[:, index[skeleton.root]]
    translations[:, 0] = _held(root[:, None], np.isfinite(root).all(-1)[:, None], np.zeros(3))[:, 0]
    axes = tuple(f"{a}rotation" for a in order.upper())
    channels = [(("Xposition", "Yposition", "Zposition") if k == 0 else ()) + axes for k in range(len(segments))]
    return Bvh(names=names, parents=parents, offsets=offsets, channels=channels, end_sites=end_sites,
               frame_time=1.0 / rate, translations=translations, rotations=rotations)
