"""How steadily each segment's twist has held relative to each neighbour over recent frames: the reference a hidden
segment's twist is held against is the neighbour it has varied least with, read from the data rather than from the
joint's kind."""

from __future__ import annotations

import numpy as np


def segment_axes(offsets: list[np.ndarray], links: list[list[tuple[int, int, np.ndarray, np.ndarray]]]) -> np.ndarray:
    """(S, 3) per segment, in its own frame, the line its twist is measured about: through its first two joint
    centres when it has two joints, else from its joint centre to its markers' centroid (a segment with no joint
    gets an arbitrary axis: it has no neighbour to compare with)."""
    axes = np.zeros((len(offsets), 3))
    axes[:, 2] = 1.0
    for k, (shape, seg_links) in enumerate(zip(offsets, links, strict=True)):
        if len(seg_links) >= 2:
            line = seg_links[1][2] - seg_links[0][2]
        elif seg_links:
            line = shape.mean(axis=0) - seg_links[0][2]
        else:
            continue
        norm = float(np.linalg.norm(line))
        if norm > 1e-6:
            axes[k] = line / norm
    return axes


def twist_angles(r_seg: np.ndarray, r_ref: np.ndarray, axes: np.ndarray) -> np.ndarray:
    """(K,) the twist (rad) of each segment's rotation relative to its reference, ``r_ref^T r_seg``, about its
    ``axes`` (K, 3) in its own frame: the angle of the twist factor of its swing-twist split, ``2 atan2(v.u, w)`` for
    the quaternion (w, v), written with the matrix's skew part and trace (both scaled by 4w) so that no quaternion is
    formed."""
    rel = np.swapaxes(r_ref, -1, -2) @ r_seg
    skew = np.stack([rel[:, 2, 1] - rel[:, 1, 2], rel[:, 0, 2] - rel[:, 2, 0], rel[:, 1, 0] - rel[:, 0, 1]], axis=1)
    trace = rel[:, 0, 0] + rel[:, 1, 1] + rel[:, 2, 2]
    return 2.0 * np.arctan2((skew * axes).sum(axis=1), 1.0 + trace)


class TwistSpread:
    """Per joint of a body, the circular spread of its two segments' relative twist about each one's axis,
    averaged exponentially over the last ``window`` samples (both segments fitted to all their markers).

    ``spread(segment, joint)`` is 1 - |mean of exp(i twist)|: 0 for a twist that never moved, near the variance (rad^2)
    / 2 for small variations; infinite before any sample, so the static order decides until the data do.
    """

    def __init__(self, joints: dict[int, tuple[int, int]], axes: np.ndarray, window: float) -> None:
        """``joints``: joint index -> (parent, child) segment indices; ``window``: samples averaged over."""
        self.pairs = np.array(list(joints.values()), dtype=int).reshape(-1, 2)  # (J, 2): parent, child
        self.axes = axes
        self.gain = 1.0 / max(window, 1.0)
        self.sums = np.zeros((len(self.pairs), 2, 3))  # per joint, per side: weight, mean cos, mean sin
        self._spreads: np.ndarray | None = None  # ``spread`` of every slot, worked out from ``sums`` when first read
        self.slot: dict[tuple[int, int], tuple[int, int]] = {}  # (segment, joint) -> (row in pairs, side)
        for row, (joint, (p, c)) in enumerate(joints.items()):
            self.slot[p, joint] = (row, 0)
            self.slot[c, joint] = (row, 1)

    def carry_on(self, previous: TwistSpread) -> None:
        """Go on from the statistics of ``previous``, a spread over the same joints."""
        self.sums = previous.sums
        self._spreads = None

    def update(self, r: np.ndarray, complete: np.ndarray) -> None:
        """Take one sample: the segments' rotations (S, 3, 3) and which were fitted to all their markers (S,)."""
        use = complete[self.pairs].all(axis=1)
        if not use.any():
            return
        p, c = self.pairs[use, 0], self.pairs[use, 1]
        seg, ref = np.concatenate([p, c]), np.concatenate([c, p])
        angle = twist_angles(r[seg], r[ref], self.axes[seg]).reshape(2, -1).T  # (J, 2): parent's, child's twist
        sample = np.stack([np.ones_like(angle), np.cos(angle), np.sin(angle)], axis=-1)
        self.sums[use] += self.gain * (sample - self.sums[use])
        self._spreads = None

    def spread(self, segment: int, joint: int) -> float:
        """How much ``segment``'s twist has varied relative to the neighbour across ``joint``."""
        if self._spreads is None:  # read for each hidden segment every frame, changed only every sample
            weight, cos, sin = np.moveaxis(self.sums, -1, 0)
            known = weight > 0
            self._spreads = np.full(weight.shape, np.inf)
            self._spreads[known] = 1.0 - np.hypot(cos[known], sin[known]) / weight[known]
        return float(self._spreads[self.slot[segment, joint]])
