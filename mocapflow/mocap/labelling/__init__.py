"""Labelling of unlabelled marker clouds: one persistent identity per physical marker.

A passive optical tracker reports per frame an unordered set of points; occlusions remove some and reflections add
ghosts. Identities are carried from frame to frame as in Schoenauer (2007) section 3.3, with the predictive tracker
of its section 5.2 in place of nearest-point matching: each track predicts its position at constant velocity, and
the optimal one-to-one assignment inside a gate (``linear_sum_assignment``) replaces the thesis's greedy
smallest-distance-first pairing.

A track whose marker disappears is never dropped. The thesis finds the tracks of one physical marker by aligning
poses on a few nearby markers (its "local approach", 4-5 markers) and comparing positions (Kirk et al.'s *Marker Set*
distance, a minimum over pairs of poses); here that comparison runs online. Every track learns from the labelled data
which other tracks keep the steadiest distance to it (its neighbours, weighted by the inverse variance of that
distance) and keeps snapshots of itself with them. When its marker is lost, the snapshot whose neighbour distances
best match the current ones is fitted to the neighbours still visible and places the hidden marker, so a reappearing
point is matched back to its old track after seconds of occlusion. Once segments are known
(:meth:`Labeller.set_segments`) a track's neighbours are its segment mates: the snapshots are then the segment's rigid
marker layout. Three more cues help: a constant-velocity coast over short dropouts; the distances to the marker's
rigid partners (two of them hold a point to a circle: a segment reduced to two visible markers still recognises its
third; a point breaking the distances to all of them is ruled out, one breaking some must lie close to where the
marker is expected); positions predicted outside (a gap filler).

Body occlusions often hide several markers of one segment at once, which then come back a few frames apart. A
returning point keeps the distances to its lost partners that come back beside it, so rigid partners seen and lost
ones count together, and where none is seen the looser neighbours must at least allow the point. A point that more
than one lost marker fits so, or that another lost marker fits by its distance to a rigid partner alone (two markers
of one segment at one distance from a third), is left to a new track rather than risk a swap; so is one whose lost
marker may already be back under another track (a marker seen now, never seen with it, fits it as loosely).

A placement from a rigid neighbourhood re-identifies at once; a looser one (neighbours across a joint) only takes a
point that has lived ``confirm_frames`` frames, so that a passing ghost cannot steal the track. Points that match no
track start tentative tracks, which become markers (or re-identify a lost one) when they live ``confirm_frames``
frames, or go back to a lost marker sooner when its rigid partners pin them (three from a point's first frame, two
from its second); the rest, short-lived ghosts, are dropped. Each frame a stream waits is a frame its marker goes
unlabelled live, so it waits 4 frames by default; offline, where a confirmed point's earlier frames are filled in,
:func:`label_sequence` waits ``offline_confirm_frames`` (5), which keeps more short-lived pieces out of its merging.
It also cuts the tracks that streaming carried across a gap onto another marker
(:func:`~.offline.split_doubtful_joins`), merges what streaming could not (the thesis's *Marker Set* merging,
:func:`merge_tracks`; then again at the joins it left in doubt, once the fragments are merged), drops tracks too short
to be markers, and follows every track from its ends, back in time and on, into the points left to no track
(:func:`~.offline.extend_tracks`: a fast foot's first frames, which streaming could not tell from its mates' with no
velocity known).

With a skeleton of the subject (``mocapflow calibrate`` on a labelled trial), :mod:`.model` names every point with
the skeleton's own marker names instead, by fitting its segments' marker layouts frame by frame; offline, where no
frame alone poses a segment, :mod:`.evidence` names its trajectories from what their frames tell together (live, its
tracks' runs from what their frames so far tell).
"""

from mocapflow.mocap.labelling.config import LabellerConfig, LabelResult
from mocapflow.mocap.labelling.labeller import Labeller
from mocapflow.mocap.labelling.offline import label_sequence, merge_tracks

__all__ = ["LabelResult", "Labeller", "LabellerConfig", "label_sequence", "merge_tracks"]
