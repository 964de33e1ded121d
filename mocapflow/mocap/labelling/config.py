"""The labeller's settings and what it answers for one frame."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TypeVar

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

STATS_HZ = 60.0  # distance statistics need no more: markers' mutual distances change slowly
VETO = 3.0  # a point breaking the distance to a rigid partner by this many tolerances cannot be that marker
CANDIDATES = 3  # snapshots fitted per lost marker
SD_FLOOR_MM = 1.0  # spread of a distance within a rigid body, from measurement noise: caps neighbour weights
UNGATED_MM = 1e6  # a gate no capture volume reaches: "nearest wins" in an assignment
FRAME_ACCEL_MM_S2 = 300_000.0
"""Acceleration of a hand or a foot between two frames that a marker followed from frame to frame may have: the real
captures' markers reach 130-370 m/s^2 (99.99th percentiles; a sprinter's feet far more, at foot strike)."""
Seconds = TypeVar("Seconds", float, np.ndarray)  # a time, or one per track


def frame_gate(least_mm: float, accel_mm_s2: float, rate: float) -> float:
    """The widest gate of a marker followed from one frame to the next at ``rate`` Hz: ``least_mm``, or, when frames
    are so far apart that a marker accelerating at ``accel_mm_s2`` strays farther from its constant-velocity course,
    that distance. At 60 Hz a hand or a foot strays up to 100 mm, and a gate of 30 mm loses it: it starts again as a
    new track, or takes a neighbour's point."""
    return max(least_mm, accel_mm_s2 / rate**2)


class LabellerConfig(BaseModel):
    """Tuning of the labeller; the defaults suit human capture at 50-250 Hz with markers 40 mm or more apart (below
    100 Hz a moving track's gate widens with the frame interval: ``follow_gate``)."""

    model_config = ConfigDict(extra="forbid")

    gate_mm: float = Field(30.0, gt=0, description="largest distance from a track's predicted position to the point it "
                           "takes, for a track seen in the previous frame")
    reid_gate_mm: float = Field(30.0, gt=0, description="largest distance from the position where a lost track's "
                                "neighbours place it (or given from outside) to the point that re-identifies it, "
                                "widened by the placement's doubt")
    instant_fit_mm: float = Field(5.0, ge=0, description="a lost marker placed by its neighbours this surely (RMS "
                                  "misfit and spread of candidate poses) is re-identified at once; looser placements "
                                  "only take points that have lived confirm_frames frames")
    frame_accel_mm_s2: float = Field(FRAME_ACCEL_MM_S2, ge=0, description="acceleration between two frames that a "
                                     "track still follows: where frames are far apart (below 100 Hz by default), a "
                                     "moving track's gate_mm widens by as far as it moved in its last frame, up to "
                                     "this times the frame interval squared (83 mm at 60 Hz)")
    max_coast_s: float = Field(0.1, ge=0, description="how long a lost track is also extrapolated at constant "
                               "velocity; after that only its neighbours can find it again")
    max_accel_mm_s2: float = Field(10_000.0, ge=0, description="acceleration bounding how fast a coasting track's gate "
                                   "grows: gate_mm + a t^2 / 2")
    max_speed_mm_s: float = Field(20_000.0, gt=0, description="fastest a marker moves; bounds the first step of a new "
                                  "point, which has no velocity yet (a sprinter's swinging foot passes 18 m/s)")
    velocity_smoothing: float = Field(0.7, gt=0, le=1, description="weight of the newest frame-to-frame velocity in a "
                                      "track's velocity estimate")
    confirm_frames: int = Field(4, ge=1, description="consecutive frames a new point must be tracked before the "
                                "stream accepts it as a marker; shorter-lived points are ghosts (a flicker of up to "
                                "three frames is not taken). Each frame waited is a frame the marker goes unlabelled "
                                "live")
    offline_confirm_frames: int = Field(5, ge=1, description="offline only: confirm_frames for label_sequence, which "
                                        "labels a confirmed point's earlier frames too, so that waiting costs it "
                                        "nothing, and the pieces of fewer short-lived points reach its merging; also "
                                        "the fewest frames two tracks must share for their distance statistics")
    neighbours: int = Field(4, ge=3, description="neighbours that place a lost marker (the thesis uses 4-5)")
    neighbour_sd_mm: float = Field(100.0, gt=0, description="largest standard deviation of the distance to a marker "
                                   "for it to serve as a neighbour; each neighbour is weighted by 1/sd^2")
    rigid_sd_mm: float = Field(3.0, gt=0, description="largest standard deviation of the distance between two markers "
                               "for them to count as one rigid body")
    rigid_tolerance_mm: float = Field(5.0, gt=0, description="a point is a lost marker's when its distances to two or "
                                      "more of the marker's rigid partners are the learnt ones within this, plus 3 sd")
    last_position_s: float = Field(1.0, ge=0, description="how long a lost track may still take a new point near "
                                   "where it was last seen when nothing else places it, or, with none of its rigid "
                                   "partners in view, on a lost partner coming back beside the point")
    rigid_min_s: float = Field(0.2, gt=0, description="time two markers must be seen together before their distance "
                               "statistics choose neighbours")
    reselect_s: float = Field(1.0, gt=0, description="how often neighbour sets are chosen again from the statistics")
    poses: int = Field(20, ge=1, description="snapshots of each marker with its neighbours kept to re-identify it")
    pose_interval_s: float = Field(0.1, gt=0, description="time between two snapshots of a marker and its neighbours")
    min_track_s: float = Field(0.5, ge=0, description="offline only: tracks seen for less than this in all, once "
                               "merged, are dropped as ghosts (the thesis drops Marker Sets under half a second) "
                               "unless they move and keep their distances to rigid partners seen with them: one "
                               "seen with it for offline_confirm_frames frames for a track seen in one unbroken "
                               "run, two seen throughout for one merged across gaps (rigid at this recording's own "
                               "noise: three times its noise floor, at least rigid_sd_mm; moving by more than that, "
                               "RMS)")
    expected_markers: int | None = Field(None, ge=1, description="number of physical markers, when known: at most "
                                         "this many tracks; beyond it new points can only re-identify lost tracks")

    def follow_gate(self, rate: float) -> float:
        """The widest gate of a track seen in the previous frame at ``rate`` Hz (``frame_gate``); each track's own
        is ``labeller.own_gates``."""
        return frame_gate(self.gate_mm, self.frame_accel_mm_s2, rate)

    def coast_gate(self, dt: Seconds, rate: float) -> Seconds:
        """The widest gate of a track coasting at constant velocity for ``dt`` s: the ``follow_gate``, widened by
        what ``max_accel_mm_s2`` could have moved it off its course since."""
        return self.follow_gate(rate) + 0.5 * self.max_accel_mm_s2 * dt**2


@dataclass
class LabelResult:
    """One frame's labelling.

    ``positions`` ``(T, 3)`` in track order, NaN where unseen; ``point_track`` the track of each input row, -1 for
    none. ``history`` lists the tracks confirmed or re-identified through a tentative track in this frame, as
    ``(track, frame_indices, positions)`` for the earlier frames (counted from 0 in calls to ``update``) in which their
    points were still unlabelled, so offline users can fill them in.
    """

    positions: np.ndarray
    point_track: np.ndarray
    history: list[tuple[int, np.ndarray, np.ndarray]] = field(default_factory=list)
    rays: np.ndarray | None = None  # (T, 6) the single-camera ray taken by each track not seen as a point, NaN rows

