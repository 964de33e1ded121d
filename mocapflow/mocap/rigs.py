"""Articulated rigs the simulator animates: a human, Schoenauer's three wooden rods, and a quadruped.

A rig is a tree of rigid segments joined by ball or hinge joints, with skin-style markers fixed on each segment.
Every segment's frame has its origin at its proximal joint centre and, in the rest pose, axes parallel to the world
(x forward, y left, z up, mm). Each rig also carries the range of motion the simulator drives it through.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np


@dataclass(frozen=True)
class Rig:
    """Topology, geometry, markers and range of motion of an articulated body. Segments are parents-first."""

    name: str
    segments: tuple[str, ...]
    parents: np.ndarray  # (S,) parent segment index, -1 for the root
    joint_names: tuple[str, ...]  # (S,) joint between parents[s] and s ("" for the root)
    joint_offsets: np.ndarray  # (S, 3) proximal joint centre of s in its parent's frame (root: rest position), mm
    joint_kinds: tuple[str, ...]  # (S,) "free" (root), "ball" or "hinge"
    hinge_axes: np.ndarray  # (S, 3) unit hinge axis in the parent's frame, zeros for other joints
    marker_labels: tuple[str, ...]  # (N,)
    marker_segment: np.ndarray  # (N,) segment index of each marker
    marker_offsets: np.ndarray  # (N, 3) marker position in its segment's frame, mm
    motion_ranges: np.ndarray  # (S, 3, 2) degrees: rotation-vector component ranges (hinge: row 0 is the angle)
    root_travel: np.ndarray  # (3, 2) world range of the root origin, mm

    @cached_property
    def levels(self) -> tuple[np.ndarray, ...]:
        """Non-root segments grouped by depth in the tree, shallowest first: each group's parents are all known
        once the previous groups are, so forward kinematics runs one vectorised step per level."""
        depth = np.zeros(len(self.segments), int)
        for s in range(1, len(self.segments)):
            depth[s] = depth[self.parents[s]] + 1
        return tuple(np.flatnonzero(depth == d) for d in range(1, depth.max() + 1))


@dataclass(frozen=True)
class _Seg:
    name: str
    parent: str | None
    joint: str
    offset: tuple[float, float, float]
    kind: str
    markers: dict[str, tuple[float, float, float]]
    ranges: tuple[tuple[float, float], ...]  # ball/free: 3 (x, y, z) ranges; hinge: 1 angle range
    axis: tuple[float, float, float] = (0.0, 0.0, 0.0)


def _build(name: str, specs: list[_Seg], travel: tuple[tuple[float, float], ...]) -> Rig:
    names = [s.name for s in specs]
    index = {n: i for i, n in enumerate(names)}
    parents = np.array([-1 if s.parent is None else index[s.parent] for s in specs])
    if parents[0] != -1 or np.any(parents[1:] >= np.arange(1, len(specs))) or np.any(parents[1:] < 0):
        raise ValueError(f"rig {name}: segments must be listed parents first, root first")
    ranges = np.zeros((len(specs), 3, 2))
    for i, s in enumerate(specs):
        ranges[i, : len(s.ranges)] = s.ranges
    labels = [label for s in specs for label in s.markers]
    if len(set(labels)) != len(labels):
        raise ValueError(f"rig {name}: marker labels are not unique")
    return Rig(
        name=name,
        segments=tuple(names),
        parents=parents,
        joint_names=tuple(s.joint for s in specs),
        joint_offsets=np.array([s.offset for s in specs], float),
        joint_kinds=tuple(s.kind for s in specs),
        hinge_axes=np.array([s.axis for s in specs], float),
        marker_labels=tuple(labels),
        marker_segment=np.array([i for i, s in enumerate(specs) for _ in s.markers]),
        marker_offsets=np.array([xyz for s in specs for xyz in s.markers.values()], float),
        motion_ranges=ranges,
        root_travel=np.array(travel, float),
    )


def _mirror(
    markers: dict[str, tuple[float, float, float]], dz: float = 0.0
) -> dict[str, tuple[float, float, float]]:
    """Right-side copy of left-side markers ("L..." -> "R..."), lowered by ``dz`` so the body is not symmetric."""
    return {"R" + k[1:]: (x, -y, z - dz) for k, (x, y, z) in markers.items()}


def _mirror_ranges(ranges: tuple[tuple[float, float], ...]) -> tuple[tuple[float, float], ...]:
    """Right-side range of a ball joint: abduction (x) and axial rotation (z) change sign."""
    (xl, xh), y, (zl, zh) = ranges
    return ((-xh, -xl), y, (-zh, -zl))


def _human() -> Rig:
    """Adult of about 1.75 m: 15 segments, 52 markers placed like a skin marker set with limb clusters."""
    hip, shoulder = ((-15, 35), (-80, 20), (-30, 30)), ((5, 100), (-100, 40), (-50, 50))
    ankle, wrist = ((-20, 20), (-30, 30), (-20, 20)), ((-25, 25), (-50, 50), (-40, 40))
    left: dict[str, dict[str, tuple[float, float, float]]] = {
        "upper_arm": {"LUA1": (-20, 65, -90), "LUA2": (-55, 50, -200), "LUA3": (30, 60, -230)},
        "forearm": {"LFA1": (-45, 40, -60), "LFA2": (40, 45, -150), "LFA3": (-30, 50, -220)},
        "hand": {"LHN1": (30, 45, -40), "LHN2": (-35, 40, -70), "LHN3": (5, 45, -120)},
        "thigh": {"LTH1": (20, 80, -120), "LTH2": (60, 55, -250), "LTH3": (10, 85, -330), "LTH4": (-50, 60, -200)},
        "shank": {"LSH1": (40, 55, -90), "LSH2": (60, 25, -200), "LSH3": (-20, 60, -310), "LSH4": (-55, 40, -160)},
        "foot": {"LHEE": (-55, 5, -55), "LTOE": (150, 10, -70), "LMT5": (90, 45, -80)},
    }
    specs = [
        _Seg("pelvis", None, "", (0, 0, 950), "free",
             {"LASI": (60, 125, 75), "RASI": (60, -125, 75), "LPSI": (-105, 45, 110), "RPSI": (-100, -45, 50)},
             ((-10, 10), (-10, 10), (-180, 180))),
        _Seg("torso", "pelvis", "lumbar", (-20, 0, 110), "ball",
             {"C7": (-85, 0, 430), "CLAV": (85, 0, 400), "STRN": (115, 0, 230), "RBAK": (-80, -70, 300)},
             ((-20, 20), (-15, 30), (-30, 30))),
        _Seg("head", "torso", "neck", (0, 0, 450), "ball",
             {"LFHD": (90, 60, 170), "RFHD": (90, -60, 170), "LBHD": (-80, 65, 160), "RBHD": (-80, -65, 100)},
             ((-30, 30), (-35, 35), (-50, 50))),
    ]
    for side, sign in (("left", 1.0), ("right", -1.0)):
        mk = {k: v if sign > 0 else _mirror(v, 0.0 if k in ("hand", "foot") else 20.0) for k, v in left.items()}
        rng = (lambda r: r) if sign > 0 else _mirror_ranges
        specs += [
            _Seg(f"{side}_upper_arm", "torso", f"{side}_shoulder", (0, sign * 185, 410), "ball", mk["upper_arm"],
                 rng(shoulder)),
            _Seg(f"{side}_forearm", f"{side}_upper_arm", f"{side}_elbow", (0, 0, -300), "hinge", mk["forearm"],
                 ((0, 120),), (0, -1, 0)),
            _Seg(f"{side}_hand", f"{side}_forearm", f"{side}_wrist", (0, 0, -260), "ball", mk["hand"], rng(wrist)),
            _Seg(f"{side}_thigh", "pelvis", f"{side}_hip", (0, sign * 88, 0), "ball", mk["thigh"], rng(hip)),
            _Seg(f"{side}_shank", f"{side}_thigh", f"{side}_knee", (0, 0, -430), "hinge", mk["shank"],
                 ((0, 120),), (0, 1, 0)),
            _Seg(f"{side}_foot", f"{side}_shank", f"{side}_ankle", (0, 0, -420), "ball", mk["foot"], rng(ankle)),
        ]
    return _build("human", specs, ((-1300, 1300), (-1300, 1300), (965, 1000)))


def _rods() -> Rig:
    """Schoenauer's articulated construction (thesis section 5): three wooden rods of about 35 cm joined by ball
    joints, three markers on carbon-fibre sticks per rod. The middle rod is the root; its joints are 359 mm apart."""
    half = 359.0 / 2
    free = ((-120, 120), (-120, 120), (-180, 180))
    swing = ((-60, 60), (-75, 75), (-75, 75))
    specs = [
        _Seg("rod2", None, "", (0, 0, 1200), "free",
             {"rod2_a": (-110, 40, 60), "rod2_b": (20, -70, 30), "rod2_c": (120, 30, -65)}, free),
        _Seg("rod1", "rod2", "rod_joint_1", (-half, 0, 0), "ball",
             {"rod1_a": (-70, 55, 25), "rod1_b": (-170, -30, 75), "rod1_c": (-280, 35, -60)}, swing),
        _Seg("rod3", "rod2", "rod_joint_2", (half, 0, 0), "ball",
             {"rod3_a": (90, -50, 40), "rod3_b": (200, 60, 45), "rod3_c": (300, -20, -70)}, swing),
    ]
    return _build("rods", specs, ((-800, 800), (-800, 800), (900, 1500)))


def _quadruped() -> Rig:
    """A large dog: trunk root with four two-segment legs, neck and head, and a tail (12 segments, 37 markers)."""
    shoulder, hip = ((-15, 15), (-40, 40), (-15, 15)), ((-15, 15), (-45, 35), (-15, 15))
    specs = [
        _Seg("trunk", None, "", (0, 0, 600), "free",
             {"TRK1": (250, 0, 110), "TRK2": (-20, 70, 120), "TRK3": (-250, -40, 100), "TRK4": (100, -90, 60)},
             ((-8, 8), (-10, 10), (-180, 180))),
        _Seg("neck", "trunk", "neck_base", (330, 0, 80), "ball",
             {"NCK1": (40, 0, 130), "NCK2": (110, 50, 120), "NCK3": (70, -55, 60)},
             ((-25, 25), (-40, 30), (-40, 40))),
        _Seg("head", "neck", "atlas", (150, 0, 200), "ball",
             {"HED1": (60, 60, 60), "HED2": (60, -60, 60), "HED3": (190, 0, 40)},
             ((-30, 30), (-35, 35), (-45, 45))),
        _Seg("tail", "trunk", "tail_base", (-360, 0, 50), "ball",
             {"TAL1": (-80, 0, 40), "TAL2": (-200, 40, 0), "TAL3": (-320, -40, -10)},
             ((-40, 40), (-50, 30), (-60, 60))),
    ]
    legs = [(end, x, side, sign) for end, x in (("fore", 250), ("hind", -280))
            for side, sign in (("left", 1), ("right", -1))]
    for k, (end, x, side, sign) in enumerate(legs):
        dz = 12.0 * k  # each leg's markers at a different height, so that legs differ by their marker layout
        tag = f"{side[0]}{end[0]}".upper()
        ranges = shoulder if end == "fore" else hip
        specs += [
            _Seg(f"{side}_{end}_upper", "trunk", f"{side}_{'shoulder' if end == 'fore' else 'hip'}",
                 (x, sign * 110, -50), "ball",
                 {f"{tag}U1": (30, sign * 60, -60 - dz), f"{tag}U2": (-40, sign * 55, -140 - dz),
                  f"{tag}U3": (20, sign * 50, -200 + dz)},
                 ranges if sign > 0 else _mirror_ranges(ranges)),
            _Seg(f"{side}_{end}_lower", f"{side}_{end}_upper", f"{side}_{'elbow' if end == 'fore' else 'stifle'}",
                 (0, 0, -250), "hinge",
                 {f"{tag}L1": (-35, sign * 45, -60 - dz), f"{tag}L2": (30, sign * 45, -150 + dz),
                  f"{tag}L3": (-25, sign * 40, -220 + dz / 2)},
                 ((0, 100),), (0, 1, 0)),
        ]
    return _build("quadruped", specs, ((-1500, 1500), (-1500, 1500), (580, 620)))


_FACTORIES = {"human": _human, "rods": _rods, "quadruped": _quadruped}
RIG_NAMES: tuple[str, ...] = tuple(_FACTORIES)


def make_rig(name: str) -> Rig:
    """The named rig (one of ``RIG_NAMES``)."""
    try:
        return _FACTORIES[name]()
    except KeyError:
        raise ValueError(f"unknown rig {name!r}; choose one of {', '.join(RIG_NAMES)}") from None
