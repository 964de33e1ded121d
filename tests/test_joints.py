"""Joint positions by distance variance, minimum-spanning-tree topology and hinge placement."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from mocapflow.mocap.joints import (
    distance_stats,
    fit_joint_variance,
    marker_centroid,
    place_on_axis,
    spanning_tree,
)


def _chain(frames: int = 300, seed: int = 0) -> dict:
    """Three segments A-B-C (4 markers each) joined by ball joints at known points, with 0.5 mm noise."""
    rng = np.random.default_rng(seed)
    local = [rng.normal(size=(4, 3)) * 50 + [0, 0, -150 * k] for k in range(3)]
    ra = Rotation.from_rotvec(rng.normal(size=(frames, 3)) * 0.6)
    rb = ra * Rotation.from_rotvec(rng.normal(size=(frames, 3)) * 0.5)
    rc = rb * Rotation.from_rotvec(rng.normal(size=(frames, 3)) * 0.5)
    ta = rng.normal(size=(frames, 3)) * 200
    ab = ra.apply([0, 0, -75]) + ta  # joint A-B: (0, 0, -75) in A's frame and B's frame
    tb = ab - rb.apply([0, 0, -75])
    bc = rb.apply([0, 0, -225]) + tb  # joint B-C: (0, 0, -225) in B's frame and C's frame
    tc = bc - rc.apply([0, 0, -225])
    markers = [np.einsum("fab,nb->fna", r.as_matrix(), m) + t[:, None]
               for r, m, t in zip((ra, rb, rc), local, (ta, tb, tc), strict=True)]
    return dict(markers=[m + rng.normal(size=m.shape) * 0.5 for m in markers], ab=ab, bc=bc)


def test_variance_cost_locates_a_ball_joint_and_ranks_it_below_a_false_one() -> None:
    chain = _chain()
    a, b, c = chain["markers"]
    both = np.concatenate([a, b], axis=1)
    start = marker_centroid(both)  # Schoenauer's start: the centroid of both segments' markers
    fit = fit_joint_variance(both, start)
    error = np.linalg.norm(fit.centres - chain["ab"], axis=1)
    assert error.mean() < 2.0
    assert fit.distance_sd < 1.0 and fit.cost < 1.0
    far = np.concatenate([a, c], axis=1)
    false = fit_joint_variance(far, marker_centroid(far))
    assert false.cost > 20 * fit.cost


def test_variance_fit_handles_gaps_and_frames_without_markers() -> None:
    chain = _chain(seed=1)
    both = np.concatenate(chain["markers"][1:], axis=1)
    both[::4, 0] = np.nan
    both[::7, 5] = np.nan
    both[10] = np.nan  # nothing seen: the centre stays unknown
    fit = fit_joint_variance(both, marker_centroid(both))
    assert np.isnan(fit.centres[10]).all()
    keep = np.arange(len(both)) != 10
    assert np.linalg.norm(fit.centres[keep] - chain["bc"][keep], axis=1).mean() < 2.0


def test_distance_stats_of_a_fixed_point() -> None:
    rng = np.random.default_rng(2)
    directions = rng.normal(size=(100, 2, 3))
    markers = directions / np.linalg.norm(directions, axis=-1, keepdims=True) * [[[100.0], [200.0]]]
    cost, mean, sd = distance_stats(np.zeros((100, 3)), markers, alpha=0.5)
    assert np.isclose(mean, 150.0) and sd < 1e-9 and np.isclose(cost, 0.5 * 150.0)


def test_spanning_tree_keeps_the_cheapest_joints_and_roots_at_the_most_connected_segment() -> None:
    # a star-and-chain body: 0 joined to 1, 2, 3 and 3 joined to 4; all other pairs are expensive
    costs = np.full((5, 5), 50.0)
    for a, b, c in [(0, 1, 1.0), (0, 2, 2.0), (0, 3, 1.5), (3, 4, 1.2), (1, 2, 9.0)]:
        costs[a, b] = costs[b, a] = c
    costs[2, 4] = costs[4, 2] = np.inf
    root, edges = spanning_tree(costs)
    assert root == 0
    assert sorted(edges) == [(0, 1), (0, 2), (0, 3), (3, 4)]
    assert edges.index((0, 3)) < edges.index((3, 4))  # parents first


def test_spanning_tree_root_tie_goes_to_the_most_central_segment() -> None:
    costs = np.full((5, 5), 100.0)
    for k in range(4):  # a chain 0-1-2-3-4: segments 1, 2, 3 all have two joints; 2 is the centre
        costs[k, k + 1] = costs[k + 1, k] = 1.0 + k
    root, edges = spanning_tree(costs)
    assert root == 2
    assert sorted(tuple(sorted(e)) for e in edges) == [(0, 1), (1, 2), (2, 3), (3, 4)]


def test_hinge_placement_levels_the_centre_with_the_neighbouring_joints() -> None:
    axis = np.array([0.0, 1.0, 0.0])
    # a knee found 60 mm off to the side along its axis; hip and ankle centres lie in the leg's plane (y = 0)
    parent, child = np.array([0.0, 60.0, -400.0]), np.array([5.0, 60.0, 200.0])
    hip, ankle = np.array([0.0, 0.0, 30.0]), np.array([0.0, 0.0, -220.0])
    p, c = place_on_axis(parent, child, axis, axis, [hip], [ankle])
    assert np.allclose(p, [0.0, 0.0, -400.0]) and np.allclose(c, [5.0, 0.0, 200.0])
    p, c = place_on_axis(parent, child, axis, axis, [], [])  # no neighbours: mid-plane of the two origins
    assert np.isclose(p @ axis + c @ axis, 0.0) and np.isclose(p @ axis, 0.0)
