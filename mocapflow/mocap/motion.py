"""A skeletal motion in memory (``Bvh``): a joint tree with per-frame local rotations and translations, as a BVH file
holds it (read and written by ``mocapflow.io.bvh``), for the algorithms that take motion data (the simulator)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation


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
