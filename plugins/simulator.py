"""Simulated optical tracker: an articulated rig in lifelike motion, with noise, occlusions and ghosts."""

from __future__ import annotations

from pydantic import Field

from mocapflow.io.bvh import read_bvh
from mocapflow.messages import MarkerFrame, SimTruth
from mocapflow.mocap.simulator import Simulator, SimulatorConfig
from mocapflow.runtime.node import Node, Output


class SimulatorNodeConfig(SimulatorConfig):
    frames: int | None = Field(default=None, ge=1, description="stop after this many frames; none: run until stopped")


class SimulatorNode(Node[SimulatorNodeConfig]):
    """Simulated tracker publishing marker frames at the configured rate, plus ground truth for evaluation."""

    Config = SimulatorNodeConfig
    outputs = {
        "markers": Output(MarkerFrame, doc="raw frames: labelled rows, or a shuffled point cloud when unlabelled; "
                                           "with cameras, single-camera markers as rays"),
        "truth": Output(SimTruth, doc="identities, true positions and joint centres of each frame"),
    }

    def setup(self) -> None:
        self.sim = Simulator(self.config, read_bvh(self.config.bvh) if self.config.bvh else None)
        self.rate = self.config.rate
        self.labels = list(self.sim.rig.marker_labels)

    def _past_end(self, index: int) -> bool:
        return self.config.frames is not None and index >= self.config.frames

    def prepare(self, index: int) -> None:
        if not self._past_end(index):
            self.sim.prepare(index)  # a step of the next block of 64 frames: a frame waits for a step, not a block

    def emit(self, index: int) -> bool:
        if self._past_end(index):
            return False
        frame = self.sim.frame(index)
        capture_ns = self.due_ns(index)  # a late frame is late from when it was due
        self.publish("markers", MarkerFrame(
            frame=index, capture_ns=capture_ns, rate=self.rate, positions=frame.points, labels=frame.labels,
            rays=frame.rays,
        ))
        if self.listened("truth"):  # an evaluation's: no graph that only runs the simulator reads it
            self.publish("truth", SimTruth(
                frame=index, capture_ns=capture_ns, labels=self.labels, identity=frame.identity,
                true_positions=frame.true_positions, joint_names=self.sim.joint_names,
                joint_centres=frame.joint_centres,
            ))
        return True
