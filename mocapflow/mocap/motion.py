"""Motion that drives a rig: a skeletal motion in memory (``Bvh``: a joint tree with per-frame local rotations and
translations, as a BVH file holds it; read and written by ``mocapflow.io.bvh``), the simulator's synthetic motion
(``SyntheticMotion``) and a BVH recording retargeted onto the rig (``BvhMotion``)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from mocapflow.errors import MotionError
from mocapflow.mocap.rigs import Rig

_WAVES = 3  # sinusoids per degree of freedom
_JOINT_HZ, _ROOT_TURN_HZ, _ROOT_TRAVEL_HZ = (0.2, 1.5), (0.05, 0.3), (0.03, 0.12)


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


def forward_kinematics(rig: Rig, local: np.ndarray, root: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World poses (R (..., S, 3, 3), t (..., S, 3)) of every segment from local rotations and the root position.

    ``local[..., s]`` rotates segment s relative to its parent (the root's is its world rotation).
    """
    rot = np.empty_like(local)
    pos = np.empty(local.shape[:-1])
    rot[..., 0, :, :], pos[..., 0, :] = local[..., 0, :, :], root
    for level in rig.levels:
        parent = rig.parents[level]
        rot[..., level, :, :] = rot[..., parent, :, :] @ local[..., level, :, :]
        offset = (rot[..., parent, :, :] @ rig.joint_offsets[level][..., None])[..., 0]
        pos[..., level, :] = offset + pos[..., parent, :]
    return rot, pos


class SyntheticMotion:
    """Each rotation component and the root position follow a smooth bounded signal spanning the rig's ranges."""

    def __init__(self, rig: Rig, seed: Sequence[int]) -> None:
        rng = np.random.default_rng(seed)
        n = len(rig.segments)
        bands = np.tile(np.array(_JOINT_HZ), (n + 1, 3, 1))
        bands[0] = _ROOT_TURN_HZ
        bands[0, 2] = _ROOT_TRAVEL_HZ  # heading changes slowly, like the path
        bands[n] = _ROOT_TRAVEL_HZ  # last row: root position
        bands[n, 2] = _JOINT_HZ  # height bobs
        self.freq = rng.uniform(bands[..., :1], bands[..., 1:], (n + 1, 3, _WAVES))
        self.phase = rng.uniform(0, 2 * np.pi, (n + 1, 3, _WAVES))
        self.amp = rng.uniform(0.5, 1.0, (n + 1, 3, _WAVES))
        self.rms = np.sqrt((self.amp**2).sum(-1) / 2)
        ranges = np.concatenate([np.radians(rig.motion_ranges), rig.root_travel[None]])
        self.low, self.span = ranges[..., 0], ranges[..., 1] - ranges[..., 0]
        self.hinge = np.array([k == "hinge" for k in rig.joint_kinds])
        self.axes = rig.hinge_axes

    def __call__(self, t: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Root position (..., 3) and local rotation vectors (..., S, 3) at time(s) t (a number or an array)."""
        at = np.asarray(t, dtype=np.float64)[..., None, None, None]
        s = (self.amp * np.sin(2 * np.pi * self.freq * at + self.phase)).sum(-1)
        value = self.low + self.span * 0.5 * (1 + np.tanh(1.2 * s / self.rms))
        rotvec = value[..., :-1, :]
        rotvec[..., self.hinge, :] = self.axes[self.hinge] * rotvec[..., self.hinge, :1]
        return value[..., -1, :], rotvec


# BVH axes (x left, y up, z forward, as in CMU and most exporters) to rig axes (x forward, y left, z up).
_BVH_TO_RIG = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
# BVH joint whose world rotation each human segment takes, by the naming schemes in use (first found wins).
_BVH_JOINTS = {
    "pelvis": ("Hips",),
    "torso": ("Spine2", "Chest2", "Spine1", "Chest", "Spine"),
    "head": ("Head",),
    "{side}_upper_arm": ("{Side}Arm", "{Side}Shoulder"),
    "{side}_forearm": ("{Side}ForeArm", "{Side}Elbow"),
    "{side}_hand": ("{Side}Hand", "{s}hand", "{Side}Wrist"),
    "{side}_thigh": ("{Side}UpLeg", "{Side}Hip", "{Side}Thigh"),
    "{side}_shank": ("{Side}Leg", "{Side}Knee", "{Side}Shin"),
    "{side}_foot": ("{Side}Foot", "{Side}Ankle"),
}
_FLOOR_MM = 15.0  # lowest marker height over a BVH clip


class BvhMotion:
    """A BVH recording retargeted onto the rig: the rig keeps its own bone lengths and takes each mapped joint's
    world orientation (corrected for the difference between the two rest poses); hinges keep the rotation about
    their axis. The clip plays forwards then backwards, so motion stays continuous however long the run."""

    def __init__(self, rig: Rig, bvh: Bvh) -> None:
        joint = [self._find(bvh, seg) for seg in rig.segments]
        world, position = bvh.world_transforms()
        rest = np.zeros_like(bvh.offsets)
        for j, p in enumerate(bvh.parents):
            rest[j] = bvh.offsets[j] + (rest[p] if p >= 0 else 0)
        c = _BVH_TO_RIG
        align = np.broadcast_to(np.eye(3), (len(rig.segments), 3, 3)).copy()
        for s in range(1, len(rig.segments)):
            children = np.flatnonzero(rig.parents == s)
            if len(children):
                bone = c @ (rest[joint[children[0]]] - rest[joint[s]])
                align[s] = Rotation.align_vectors(bone[None], rig.joint_offsets[children[0]][None])[0].as_matrix()
        glob = c @ world[:, joint] @ c.T @ align  # (F, S, 3, 3) rig segment world rotations
        local = glob.copy()
        local[:, 1:] = np.swapaxes(glob[:, rig.parents[1:]], -1, -2) @ glob[:, 1:]
        quat = Rotation.from_matrix(local.reshape(-1, 3, 3)).as_quat().reshape(len(local), -1, 4)
        for s in np.flatnonzero(np.array(rig.joint_kinds) == "hinge").tolist():
            angle = 2 * np.arctan2(quat[:, s, :3] @ rig.hinge_axes[s], quat[:, s, 3])
            angle = (angle + np.pi) % (2 * np.pi) - np.pi
            quat[:, s] = Rotation.from_rotvec(angle[:, None] * rig.hinge_axes[s]).as_quat()
        leg = [rig.segments.index(f"left_{k}") for k in ("thigh", "shank", "foot")]  # scale: hip to ankle
        rig_leg = np.linalg.norm(rig.joint_offsets[leg[1:]], axis=1).sum()
        bvh_leg = np.linalg.norm(np.diff(rest[[joint[k] for k in leg]], axis=0), axis=1).sum()
        root = position[:, joint[0]] @ c.T * (rig_leg / bvh_leg)
        root[:, :2] -= root[:, :2].mean(0)
        rot = Rotation.from_quat(quat.reshape(-1, 4)).as_matrix().reshape(local.shape)
        wrot, wpos = forward_kinematics(rig, rot, root)
        lowest = (np.einsum("fnij,nj->fni", wrot[:, rig.marker_segment], rig.marker_offsets)
                  + wpos[:, rig.marker_segment])[..., 2].min()
        root[:, 2] += _FLOOR_MM - lowest
        self.quat, self.root, self.frame_time = quat, root, bvh.frame_time
        step = Rotation.from_quat(quat[:-1].reshape(-1, 4)).inv() * Rotation.from_quat(quat[1:].reshape(-1, 4))
        self.step = step.as_rotvec().reshape(len(quat) - 1, -1, 3)

    @staticmethod
    def _find(bvh: Bvh, segment: str) -> int:
        side = segment.split("_", 1)[0] if segment.startswith(("left_", "right_")) else ""
        key = segment.replace(side, "{side}", 1) if side else segment
        candidates = [n.format(Side=side.capitalize(), s=side[:1]) for n in _BVH_JOINTS[key]]
        for name in candidates:
            try:
                return bvh.index(name)
            except KeyError:
                continue
        raise MotionError(f"no BVH joint for the rig's {segment} (looked for {', '.join(candidates)})")

    def __call__(self, t: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Root position (..., 3) and local rotation vectors (..., S, 3) at time(s) t (a number or an array)."""
        at = np.asarray(t, dtype=np.float64)
        last = len(self.quat) - 1
        if last == 0:
            rotvec = Rotation.from_quat(self.quat[0]).as_rotvec()
            return np.broadcast_to(self.root[0], (*at.shape, 3)), np.broadcast_to(rotvec, (*at.shape, *rotvec.shape))
        u = (at / self.frame_time) % (2 * last)
        u = np.where(u > last, 2 * last - u, u)
        k = np.minimum(u.astype(np.intp), last - 1)
        a = (u - k)[..., None]
        rot = Rotation.from_quat(self.quat[k]) * Rotation.from_rotvec(a[..., None] * self.step[k])
        return (1 - a) * self.root[k] + a * self.root[k + 1], rot.as_rotvec()
