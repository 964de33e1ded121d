"""What the filler remembers of a body's recent motion: its segments' poses, sampled from the frames where each was
seen whole, which feed the twist statistics (``twist.TwistSpread``: which neighbour a hidden segment's twist is held
against) and the kinematic models (``kinematic.LearntPlacement``: where a hidden segment is, learnt from its
neighbours)."""

from __future__ import annotations

import numpy as np

from mocapflow.mocap.filling.body import Body, same_segments
from mocapflow.mocap.filling.config import FillerConfig
from mocapflow.mocap.filling.kinematic import LearntPlacement
from mocapflow.mocap.filling.twist import TwistSpread, segment_axes


class MotionMemory:
    """The poses of ``body``'s segments sampled at ``config.pose_sample_hz``, with the statistics learnt from them.

    A memory built for a body with the same segments, markers and shapes as the ``previous`` one's (a learned body
    that only grew joints) carries on from it."""

    def __init__(self, body: Body, rate: float, config: FillerConfig, previous: MotionMemory | None) -> None:
        self.body = body
        self.every = max(1, round(rate / config.pose_sample_hz))  # frames between two samples
        samples = rate / self.every  # per second
        self.segments = np.arange(len(body.members))
        self.frame: int = previous.frame if previous is not None else 0
        self.twist = TwistSpread({j: (jt.parent, jt.child) for j, jt in enumerate(body.joints) if jt is not None},
                                 segment_axes(body.offsets, body.links), config.twist_window_s * samples)
        self.kinematic = LearntPlacement(len(body.members), max(2, round(config.kinematic_window_s * samples)),
                                         round(config.min_joint_s * samples), config.novelty)
        if previous is not None and same_segments(previous.body, body):
            self.kinematic.history = previous.kinematic.history
            if self.twist.slot.keys() == previous.twist.slot.keys():
                self.twist.carry_on(previous.twist)

    def observe(self, z: np.ndarray, seen: np.ndarray) -> None:
        """Take a frame (N, 3) and which of its markers were observed; a sampled frame's segments seen whole are
        remembered."""
        self.frame += 1
        if self.frame % self.every or not self.twist.slot:
            return
        fit = self.body.fit_for(seen, self.segments)
        r, t, ok = fit(z)
        complete = ok & fit.complete
        self.twist.update(r, complete)
        self.kinematic.history.add(r, t, complete)
