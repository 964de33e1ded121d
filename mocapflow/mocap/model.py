"""Body models learnt from data: segments (rigid marker groups) and the skeleton (segments joined by joints).

Local frame convention shared by every algorithm: a segment's local frame has its origin at the centroid of its
markers in the reference pose and axes parallel to the world axes in that pose. A segment's pose in a frame is the
rigid transform (R, t) with ``world = R @ local + t``. ``marker_offsets`` and joint offsets are in these frames, in mm.
These models are also the messages that carry them and the schema of SKELETON.json.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, FiniteFloat

Vec3 = tuple[FiniteFloat, FiniteFloat, FiniteFloat]  # a NaN offset or axis is no place: refused on reading


class Segment(BaseModel):
    """A rigid group of markers (a limb, a rod): markers that keep their mutual distances."""

    model_config = ConfigDict(extra="forbid")

    name: str
    markers: list[str] = Field(description="labels of the markers on this segment")
    marker_offsets: list[Vec3] | None = Field(
        default=None, description="marker positions in the segment's local frame (mm), same order as markers"
    )
    marker_spread_mm: list[float] | None = Field(
        default=None, description="how far each marker strays from its offset: RMS distance from where the "
                                  "segment's fitted pose puts it over the calibration data (mm), same order as "
                                  "markers; skin and soft tissue make it larger than the noise")
    rigidity_mm: float | None = Field(
        default=None, description="how rigid the markers were: standard deviation of their mutual distances over "
                                  "the calibration data, mean over pairs (mm)")


class Joint(BaseModel):
    """A centre of rotation between two segments, with the quality of its estimate."""

    model_config = ConfigDict(extra="forbid")

    name: str
    parent: str = Field(description="name of the parent segment (towards the root)")
    child: str = Field(description="name of the child segment")
    kind: Literal["ball", "hinge"] = "ball"
    parent_offset: Vec3 | None = Field(default=None, description="centre of rotation in the parent's local frame (mm)")
    child_offset: Vec3 | None = Field(default=None, description="centre of rotation in the child's local frame (mm)")
    axis: Vec3 | None = Field(default=None, description="hinge axis in the parent's local frame (unit vector)")
    cost: float | None = Field(default=None, description="joint cost used for the topology (lower is better)")
    distance_mean: float | None = Field(default=None, description="mean marker-to-joint distance (mm)")
    distance_sd: float | None = Field(
        default=None, description="mean standard deviation of marker-to-joint distance (mm)")
    gap_mm: float | None = Field(
        default=None, description="how well the two segments agree on the centre: RMS distance between where the "
                                  "parent's pose and where the child's put it over the calibration data (mm); large "
                                  "where the body is no ball joint (a bending spine, a shoulder girdle) or skin "
                                  "moves the markers")
    rotation_deg: float | None = Field(
        default=None, description="range of motion seen: RMS rotation of the child relative to the parent about "
                                  "its mean (deg); under 2 the joint could not be located and sits between the "
                                  "segments' closest markers")
    uncertainty_mm: float | None = Field(
        default=None, description="how far the centre could be off along its weakest direction: the shift a misfit "
                                  "as large as the fit's residual can cause (mm; 10000: unbounded, as for an exact "
                                  "hinge or a joint too still to locate)")
    located: bool | None = Field(
        default=None, description="whether the data locate the centre (uncertainty within 20 mm); a joint that is "
                                  "not located sits where a rule put it (on a hinge's axis level with its "
                                  "neighbours, between the segments' closest markers), not where the data did")
    motion_sd_deg: Vec3 | None = Field(
        default=None, description="SD of the child's rotation relative to the parent about the three principal axes "
                                  "of that rotation, largest first (deg): what motion the data held")
    posture: Vec3 | None = Field(
        default=None, description="how the two segments mostly stood: the child's mean rotation relative to the "
                                  "parent over the calibration data, as a rotation vector in the parent's local frame "
                                  "(deg); it tells a segment of two markers from its mirror image the first time it "
                                  "is found")


class SegmentModel(BaseModel):
    """Which marker belongs to which segment; published by the clusterer."""

    model_config = ConfigDict(extra="forbid")

    segments: list[Segment]


class SkeletonModel(BaseModel):
    """A parameterised skeleton: segments, the joints that form a tree, and its root. Saved as SKELETON.json."""

    model_config = ConfigDict(extra="forbid")

    name: str = "skeleton"
    units: Literal["mm"] = "mm"
    segments: list[Segment]
    joints: list[Joint]
    root: str = Field(description="name of the root segment")
