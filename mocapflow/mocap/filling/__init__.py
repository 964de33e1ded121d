"""Real-time occlusion filling: a Kalman filter per marker fed by rigid-body constraints (Aristidou 2008, ch. 5).

Every marker has a constant-velocity Kalman filter (``kalman.ConstantVelocityBank``). An observed marker is its own
measurement. A missing marker on a segment gets a measurement built from what is still visible, by occlusion case
(5.3), and its filter's estimate is the output:

- two or more markers of its segment visible (code 3): with three or more anchor points the segment's pose is fitted
  to them; with two, each marker goes to the point nearest its rotated-offset estimate on the circle where the
  spheres about the two anchors meet (5.3.2, appendix C);
- one visible (code 4): the rotated offset from that marker (5.3.3);
- none visible, a neighbouring segment with visible markers (code 5): the rotated offset from their shared centre of
  rotation, placed by the neighbour (5.3.4, eq. 4.35);
- the neighbours hidden too (code 6): placed through a joint of a neighbour itself estimated, or, with no neighbour
  at all, turned on by its last rotor (constant rotor, 5.3.4);
- a marker seen by one camera only (code 7): its estimate is projected onto that camera's ray (5.3.5) before the
  other missing markers of its segment are placed, so they can lean on it (6.2.4);
- no usable segment (code 2): its filter's prediction alone.

Changes to the thesis, each backed by its results (tables 6.1-6.6) or needed for gaps of seconds:

- Offsets come from the segment model (fixed local marker positions), not from the previous frame's vectors, so the
  inter-marker distances cannot drift over a long gap.
- A centre of rotation is one more anchor point of its segment, also while one or two of its markers remain visible
  (``joint_anchors="partial"``; the thesis's use, whole segment hidden only, is ``"hidden"``). With a skeleton this
  is the largest gain: the rotation about the line through two visible markers is otherwise unknown.
- The rotation left free by fewer than three anchors is held relative to the posed neighbour the segment's twist has
  varied least with over the last seconds (``twist``; a hinge first, then the parent, until the data say), not
  extrapolated in the world: a held joint angle errs far less than a constant rotor
  over seconds (``hidden_rotation``). With two anchors the hold is a swing-twist split about the anchor line taken
  when the gap starts, so the twist cannot creep as the line moves (a frame-to-frame minimal rotation accumulates
  holonomy over a walking cycle).
- A whole hidden segment with two or more visible neighbours is also anchored on where a kinematic model learnt over
  the last seconds puts its markers (``kinematic``: a regression on the neighbours' relative poses, used only for
  configurations like those it learnt; code 8, ``FillCase.LEARNT``).
- A single-camera marker is also slid along its ray to match its distances to the visible markers of its segment,
  with the projected estimate as a prior (appendices D and E combined with 5.3.5: ``ray_distances``).
- Joint centres (tables 6.1, 6.2): from the side whose markers are all visible when only one is, the mean of both
  sides otherwise. Learned joint offsets (no skeleton) are updated from frames with predicted markers only while
  each side keeps a visible marker, never from a fully hidden segment (table 6.3; ``update_joint_offsets``).
- A marker predicted from its past alone (its filter, or a constant rotor with nothing visible) coasts to rest
  (``coast_decay_s``) and is given up after ``extrapolate_max_s``, rather than flying off for seconds.

The filler never reads a future frame: ``update`` uses the current frame and its own state only, so filling a
recording frame by frame (``fill_sequence``) gives exactly what a live stream would have given. A file may also be
filled both ways (``fill_both_ways``, ``mocapflow fill --offline``): the same filler run forwards and backwards, blended
across each gap, which uses the frames after a gap as no live stream can, and weighed against the whole body's
postures (``posture``; code 9, ``FillCase.POSTURE``) by their errors on trial gaps.
"""


from mocapflow.mocap.filling.config import FillerConfig, FillResult
from mocapflow.mocap.filling.filter import GapFiller
from mocapflow.mocap.filling.geometry import nearest_on_circle, project_on_rays
from mocapflow.mocap.filling.learner import is_complete
from mocapflow.mocap.filling.offline import FilledRecording, fill_both_ways, fill_recording, fill_sequence
from mocapflow.mocap.flags import FillCase

__all__ = ["FillCase", "FillResult", "FilledRecording", "FillerConfig", "GapFiller", "fill_both_ways", "fill_recording",
           "fill_sequence", "is_complete", "nearest_on_circle", "project_on_rays"]
