"""The compiled arithmetic, made ready before it is needed.

The per-frame arithmetic of the live stages, the labeller's assignments and track statistics (``labelling``), the
occlusion filler's Kalman filters (``kalman``), the rigid fits (``rigidfit``) and the skeleton's pose solve
(``solve``), is compiled by numba the first time it runs, and numba keeps what it compiled in a cache beside the code
(or in the user's cache folder where that is not writable). Loading it costs a fraction of a second; compiling it, on
a machine that has never run it, about half a minute of CPU. A live graph must not pay that on its first frames, nor in
four processes at once. Each loader here runs one stage's kernels once, in every form the project calls them, on a
tiny two-segment body (``compile_all``: every stage's). A node names its stage's loaders (``Node.kernels``); its
process runs them before the node's setup, and the launcher runs those of its graph's nodes before it starts any.
Each process loads no more than its nodes use, so one that restarts is that much sooner back on the stream.
"""

from __future__ import annotations

from collections.abc import Iterator
from functools import cache

import numpy as np

from mocapflow.mocap.filling import FillerConfig, GapFiller
from mocapflow.mocap.labelling import Labeller, LabellerConfig
from mocapflow.mocap.labelling.labeller import own_gates
from mocapflow.mocap.labelling.model import TrackedModelLabeller, could_hold
from mocapflow.mocap.model import Joint, Segment, SkeletonModel
from mocapflow.mocap.reacquire import Reacquirer
from mocapflow.mocap.rigidfit import fit_one, fit_pose, kabsch, quaternion_matrices, rotor
from mocapflow.mocap.solve import PoseSolver

SQUARE = [[0.0, 0.0, 0.0], [100.0, 0.0, 0.0], [0.0, 100.0, 0.0]]
LAYOUT = np.array([*SQUARE, [0.0, 0.0, 100.0], [100.0, 0.0, 100.0]])  # two segments' markers, at rest
SKELETON = SkeletonModel(
    segments=[Segment(name="a", markers=["a1", "a2", "a3"], marker_offsets=SQUARE),
              Segment(name="b", markers=["b1", "b2"], marker_offsets=SQUARE[:2])],
    joints=[Joint(name="a-b", parent="a", child="b", parent_offset=[0.0, 0.0, 50.0], child_offset=[0.0, 0.0, -50.0])],
    root="a")


def compile_all() -> None:
    """Run every compiled kernel once (each is then loaded from numba's cache, or compiled and cached); once a
    process, as each stage's loader runs once."""
    compile_fits()
    compile_labelling()
    compile_model_labelling()
    compile_filling()


@cache
def compile_fits() -> None:
    """The rigid fits and the skeleton's pose solve (the skeleton publisher, the joint estimator); once a process."""
    frames = np.array([LAYOUT] * 3)
    frames[1, 2:] = np.nan  # the root short of markers: trilateration; the child on its line: a held rotation
    solver = PoseSolver(SKELETON, ["a1", "a2", "a3", "b1", "b2"])
    solver(frames[:1])
    solver(frames, progress=lambda *_: None)
    local = np.array(SQUARE)
    fit_pose(local, frames[:, :3], hold=True)
    fit_pose(local[None], frames[:, None, :3], local[:1], frames[:, None, 0], hold=True)
    rotor(local, local, np.ones(3))
    fit_one(local, local, np.ones(3))
    kabsch(local[None], local[None], np.ones((1, 3)))
    quaternion_matrices(np.array([0.0, 0.0, 0.0, 1.0]))


@cache
def compile_labelling() -> None:
    """The labeller's assignments and track statistics, and the rigid fit that finds its markers again by their
    layouts after a restart or a blackout (``reacquire``); once a process."""
    labeller = Labeller(LabellerConfig(), 100.0)
    for i, (points, far) in enumerate(_turning()):
        labeller.update(np.vstack([points[::-1], far]), i / 100)
    labeller.update(np.vstack([points, points[:1] + 1.0]), 3.0)  # two points by a marker: the optimal assignment
    reacquire = Reacquirer(labeller)
    for i, (points, _) in zip(range(2), _turning(), strict=False):
        reacquire(points, 4.0 + i / 100)
    own_gates(1.0, 2.0, np.zeros((1, 3)), np.zeros(1))  # as reacquire follows the tracks it found


@cache
def compile_model_labelling() -> None:
    """The search for a segment's marker layout among a frame's points, by which a skeleton's names are given
    (``labelling.model``); once a process."""
    compile_labelling()
    labeller = TrackedModelLabeller(SKELETON, 100.0)
    for i, (points, far) in enumerate(_turning()):
        labeller.update(np.vstack([points[::-1], far]), i / 100)
    could_hold(labeller.model.segments[0], LAYOUT, 3)  # as a segment short of a marker looks for more


@cache
def compile_filling() -> None:
    """The filler's Kalman filters and its segments' rigid fits; once a process."""
    compile_fits()
    filler = GapFiller([m for seg in SKELETON.segments for m in seg.markers], 100.0, FillerConfig(), SKELETON)
    for points, _ in _turning():
        filler.update(points)
        filler.predict_next()


def _turning() -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """3 s of the two segments turning at 100 Hz, a marker hidden for a while and a new point far off meanwhile:
    long enough for the labeller to learn neighbours, weigh the new point against the lost marker, young and
    confirmed, and take the marker back, and for the filler to fill it. Each frame's markers and its far point (none
    or one)."""
    for i in range(300):
        c, s = np.cos(i / 50), np.sin(i / 50)
        points = LAYOUT @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]).T + [i, 0.0, 0.0]
        if 200 <= i < 220:
            points[4] = np.nan
        yield points, (np.array([[5000.0, 0.0, float(i)]]) if 205 <= i < 215 else np.empty((0, 3)))
