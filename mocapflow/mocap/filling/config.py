"""What the occlusion filler is told and what it answers: its settings, the per-marker fill cases and one filled
frame."""

from __future__ import annotations

from collections.abc import Callable
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field


class FillerConfig(BaseModel):
    """Noise levels, constraint choices and online-learning settings of the filler."""

    model_config = ConfigDict(extra="forbid")

    accel_sd: float = Field(
        50000.0, gt=0, description="white-noise acceleration of the constant-velocity model (mm/s^2)")
    initial_speed_sd: float = Field(1000.0, gt=0, description="spread of a new marker's unknown speed (mm/s)")
    observed_sd: float = Field(0.5, gt=0, description="measurement noise of an observed marker (mm)")
    rigid_sd: float = Field(0.5, gt=0, description="noise of an estimate from two or more visible markers (mm)")
    offset_sd: float = Field(1.0, gt=0, description="noise of an estimate from one visible marker (mm)")
    joint_sd: float = Field(1.0, gt=0, description="noise of an estimate through a centre of rotation (mm)")
    rotor_sd: float = Field(5.0, gt=0, description="noise of a constant-rotor estimate (mm)")
    ray_sd: float = Field(2.0, gt=0, description="noise of an estimate projected on a camera ray (mm)")
    ray_distances: bool = Field(
        True, description="move a single-camera marker along its ray to match its distances to the visible markers "
        "of its segment (appendices D, E), not only project the estimate on the ray (5.3.5)")
    joint_anchors: Literal["hidden", "partial"] = Field(
        "partial", description="use a neighbour's centre of rotation only when the whole segment is hidden, or also "
        "when one or two of its markers remain visible")
    joint_weight: float = Field(0.5, gt=0, description="weight of a centre of rotation against a marker in a fit")
    hidden_rotation: Literal["joint", "rotor"] = Field(
        "joint", description="rotation of a segment placed through a single anchor: keep its rotation relative to "
        "the posed neighbour (joint angles held), or turn on by its last rotor in the world (the thesis's constant "
        "rotor)")
    pose_sample_hz: float = Field(
        10.0, gt=0, description="rate at which the segments' poses are sampled for the twist statistics and the "
        "kinematic models (the frame rate at most)")
    twist_window_s: float = Field(
        5.0, gt=0, description="seconds over which each segment's twist relative to each neighbour is averaged: a "
        "segment placed through its joints holds its twist relative to the neighbour it varied least with")
    kinematic_model: bool = Field(
        True, description="place a whole hidden segment by a regression of its markers in a visible neighbour's "
        "frame on the other visible neighbours' poses, learnt over the last kinematic_window_s, while the present "
        "configuration lies inside what was learnt (else through its joints)")
    kinematic_window_s: float = Field(5.0, gt=0, description="seconds of past frames the kinematic model learns from")
    kinematic_sd: float = Field(2.0, gt=0, description="noise of an estimate by the learnt kinematic model (mm)")
    novelty: float = Field(
        1.5, gt=0, description="a configuration is new to the kinematic model when its Mahalanobis distance to the "
        "learnt ones exceeds this many times the largest among them")
    coast_decay_s: float | None = Field(
        0.25, gt=0, description="time constant (s) of the velocity decay of a marker tracked by its filter alone")
    extrapolate_max_s: float | None = Field(
        0.5, gt=0, description="give up a marker predicted from its past alone (its own filter, or a constant rotor "
        "with nothing visible to anchor its segment) after this long (s); none: never")
    learn: bool = Field(True, description="learn whatever the skeleton does not give (segments, marker offsets, "
                        "joints) from the frames seen so far")
    cluster_method: Literal["spectral", "distance-threshold"] = Field(
        "spectral", description="how markers are grouped into segments when no skeleton gives them")
    rigid_tolerance: float = Field(
        5.0, gt=0, description="largest SD of a within-segment marker distance, for distance-threshold grouping (mm)")
    learn_stride: int = Field(4, ge=1, description="frames between two samples of marker distances and poses")
    learn_window_s: float = Field(20.0, gt=0, description="seconds of samples behind the grouping")
    learn_warmup_s: float = Field(2.0, gt=0, description="seconds of samples before the first grouping")
    regroup_s: float = Field(2.0, gt=0, description="seconds between updates of the learned model (the grouping "
                             "is checked up to four times less often while it holds)")
    min_joint_rotation_deg: float = Field(
        5.0, gt=0, description="least RMS relative rotation of two segments before a joint between them is trusted")
    min_joint_s: float = Field(2.0, gt=0, description="seconds of usable frames before a learned joint is trusted")
    outlier_mm: float = Field(
        1000.0, gt=0, description="a sample this far from where its marker, seen in the previous frame, is predicted "
        "is an outlier (a reflection, a glitch) and treated as missing, not trusted")
    update_joint_offsets: Literal["observed", "partial", "always"] = Field(
        "partial", description="frames that update learned joint offsets: both sides fully observed; also with "
        "predicted markers while each side keeps one visible (tables 6.1-6.3); or every frame")


class FillResult:
    """One filled frame: ``positions`` (N, 3), NaN only where unfillable; ``flags`` (N,) uint8 ``FillCase`` codes;
    ``joint_centres`` (J, 3) when joints are known (rows named by ``GapFiller.joint_names``), else None.

    Joint centres are computed when first read, so a caller that never reads them does not pay for them.
    """

    __slots__ = ("_centres", "flags", "positions")

    def __init__(self, positions: np.ndarray, flags: np.ndarray,
                 joint_centres: np.ndarray | Callable[[], np.ndarray] | None) -> None:
        self.positions = positions
        self.flags = flags
        self._centres = joint_centres

    @property
    def joint_centres(self) -> np.ndarray | None:
        if callable(self._centres):
            self._centres = self._centres()
        return self._centres
