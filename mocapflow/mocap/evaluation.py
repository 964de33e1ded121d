"""Scoring tools for tests and benchmarks: a labelling (tracks, or markers named from a skeleton) against the true
identities of its points, and a labelled recording turned back into what a passive tracker reports."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from mocapflow.mocap.labelling.offline import source_rows


@dataclass
class LabellingScore:
    """How a labelling compares with the true identities of its points.

    Each track stands for the true marker it most often holds (majority vote). ``accuracy`` is the share of real
    points given the track that stands for their marker (so unlabelled points count as wrong); ``swaps`` counts the
    times a track moves from one true marker to another; ``fragments`` the tracks beyond one per true marker;
    ``unlabelled_at_first`` the share of real points left unlabelled because their marker had not yet been labelled
    in any frame (a labeller that tells markers from ghosts by how long they live cannot name those).
    """

    accuracy: float
    assigned: float
    swaps: int
    ghosts_rejected: float
    tracks: int
    ghost_tracks: int
    fragments: int
    markers_found: int
    markers_true: int
    unlabelled_at_first: float

    def summary(self) -> str:
        """One line for reports and benchmarks."""
        return (f"accuracy {100 * self.accuracy:.3f} %, assigned {100 * self.assigned:.3f} %, swaps {self.swaps}, "
                f"ghosts rejected {100 * self.ghosts_rejected:.2f} %, {self.tracks} tracks for "
                f"{self.markers_found}/{self.markers_true} markers ({self.fragments} fragments, "
                f"{self.ghost_tracks} ghost tracks)")


@dataclass
class NamingScore:
    """How names given from a skeleton compare with the true identities of the points: of the ``total`` real points,
    ``right`` carry their own marker's name and ``wrong`` another's; ``known`` of them are points of markers the
    labelling has a name for."""

    right: int
    wrong: int
    total: int
    known: int


def score_naming(named: np.ndarray, names: Sequence[str], points: Sequence[np.ndarray],
                 identity: Sequence[np.ndarray], labels: Sequence[str]) -> NamingScore:
    """Score the named markers ``(F, N, 3)`` (``names``, NaN where unnamed) labelled from ``points`` (per frame
    ``(M, 3)``) against ``identity`` (per frame the true marker of each row, an index into ``labels``; -1 for a
    ghost). A named position is traced back to the input row it was copied from."""
    index = np.array([labels.index(n) if n in labels else -2 for n in names], dtype=int)
    right = wrong = total = known = 0
    for f, (rows, ids) in enumerate(zip(points, identity, strict=True)):
        ids = np.asarray(ids)
        real = np.flatnonzero(ids >= 0)
        total += len(real)
        known += int(np.isin(ids[real], index).sum())
        source = source_rows(named[f], np.asarray(rows, dtype=float)[real])  # the true point each marker was named on
        hit = np.flatnonzero(source >= 0)
        right += int((index[hit] == ids[real][source[hit]]).sum())
        wrong += int((index[hit] != ids[real][source[hit]]).sum())
    return NamingScore(right, wrong, total, known)


def held_markers(tracks: np.ndarray, points: Sequence[np.ndarray], identity: Sequence[np.ndarray],
                 markers: int) -> tuple[np.ndarray, np.ndarray, int]:
    """The true marker each track of ``tracks`` ``(F, T, 3)`` holds in each frame, ``(F, T)`` (-1 a ghost, -2
    nothing), traced back to the row of ``points`` it was copied from; which true markers are seen in each frame,
    ``(F, markers)``; and how many ghost points there are (arguments as for :func:`score_labelling`)."""
    n_frames, n_tracks, _ = tracks.shape
    held = np.full((n_frames, n_tracks), -2)
    ghosts = 0
    seen = np.zeros((n_frames, markers), bool)
    for f in range(n_frames):
        rows = np.asarray(points[f], dtype=float).reshape(-1, 3)
        ids = np.asarray(identity[f])
        present = np.isfinite(rows).all(axis=1)
        seen[f, ids[present & (ids >= 0)]] = True
        ghosts += int((present & (ids < 0)).sum())
        on = np.flatnonzero(np.isfinite(tracks[f, :, 0]))
        source = source_rows(tracks[f, on], np.where(present[:, None], rows, np.nan))
        if (source < 0).any():
            raise ValueError(f"frame {f}: a labelled position is not one of the input points")
        held[f, on] = ids[source]
    return held, seen, ghosts


def track_markers(held: np.ndarray, markers: int) -> np.ndarray:
    """The marker each track stands for, ``(T,)``: the true marker it holds most (-1 for a track of ghosts only)."""
    return np.array([np.bincount(h[h >= 0], minlength=markers).argmax() if (h >= 0).any() else -1
                     for h in held.T], dtype=int)


def score_labelling(tracks: np.ndarray, points: Sequence[np.ndarray], identity: Sequence[np.ndarray],
                    markers: int) -> LabellingScore:
    """Score trajectories ``(F, T, 3)`` labelled from ``points`` (per frame ``(M, 3)``) against ``identity``.

    ``identity`` gives per frame the true marker index of each row of ``points``, -1 for a ghost; ``markers`` is the
    number of true markers. A labelled position is traced back to the input row it was copied from.
    """
    n_frames, n_tracks, _ = tracks.shape
    held, seen, ghosts = held_markers(tracks, points, identity, markers)
    majority = track_markers(held, markers)
    real = int(seen.sum())
    right = int(((held >= 0) & (held == majority[None])).sum())
    swaps = sum(int(np.count_nonzero(np.diff(h[h >= 0]))) for h in held.T)
    found = majority[majority >= 0]
    labelled = np.zeros((n_frames, markers), bool)
    frames, owned = np.nonzero(held >= 0)
    labelled[frames, held[frames, owned]] = True
    first = np.where(labelled.any(axis=0), labelled.argmax(axis=0), n_frames)
    before = int(seen[np.arange(n_frames)[:, None] < first[None]].sum())
    return LabellingScore(
        accuracy=right / max(real, 1), assigned=int((held >= 0).sum()) / max(real, 1), swaps=swaps,
        ghosts_rejected=1.0 - int((held == -1).sum()) / max(ghosts, 1), tracks=n_tracks,
        ghost_tracks=int((majority < 0).sum()), fragments=len(found) - len(set(found.tolist())),
        markers_found=len(set(found.tolist())), markers_true=markers, unlabelled_at_first=before / max(real, 1),
    )


STRESS: dict[str, Any] = {"gaps_per_s": math.log(1.5) / 1.1, "long_fraction": 1.0, "long_s": (0.2, 2.0),
                          "ghosts": 0.2, "ghost_frames": 1}
"""The labelling benchmark's stress damage, ``unlabel``'s arguments: independent gaps of 0.2-2 s (mean 1.1 s) starting
at a rate that hides a marker a third of the time (1 - exp(-rate * 1.1 s) = 1/3), and one-frame ghosts, Poisson 0.2
per frame (one or more in 18 % of frames)."""


def unlabel(positions: np.ndarray, rate: float, seed: int, gaps_per_s: float = 0.05, long_fraction: float = 0.3,
            ghosts: float = 1.0, long_s: tuple[float, float] = (0.5, 2.0), ghost_frames: int = 3,
            stationary: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """A labelled recording ``(F, N, 3)`` as a passive tracker would report it, to test labelling against truth.

    Adds occlusions (``gaps_per_s`` per marker per second, independent; a ``long_fraction`` of them ``long_s``
    seconds long, the others 1-9 frames; ``stationary``: also gaps already under way at the first frame, as in a
    capture that began earlier, so that the share hidden is the same from first frame to last; otherwise gaps begin
    at the first frame or later, and a capture a few gaps long is hidden less than ``gaps_per_s`` says), ghost
    points (Poisson, ``ghosts`` new per frame, each living 1 to ``ghost_frames`` frames, 20-300 mm from a random
    marker, with 0.5 mm jitter) and shuffles the rows of every frame. Returns points ``(F, W, 3)`` padded with NaN
    and identity ``(F, W)``: the true marker index of each row, -1 for ghosts and padding.
    """
    rng = np.random.default_rng(seed)
    n_frames, n_markers, _ = positions.shape
    seen = np.isfinite(positions).all(axis=2)
    lead = max(int(long_s[1] * rate), 9) if stationary else 0  # no gap is longer
    for marker in range(n_markers):
        for _ in range(rng.poisson(gaps_per_s * (n_frames + lead) / rate)):
            long = rng.random() < long_fraction
            length = int(rng.uniform(*long_s) * rate) if long else int(rng.integers(1, 10))
            start = int(rng.integers(-lead, n_frames))
            seen[max(start, 0):max(start + length, 0), marker] = False
    clouds: list[np.ndarray] = []
    owners: list[np.ndarray] = []
    alive: list[tuple[int, np.ndarray]] = []  # (last frame, position) of each ghost
    for f in range(n_frames):
        visible = np.flatnonzero(seen[f])
        for _ in range(rng.poisson(ghosts) if len(visible) else 0):
            direction = rng.standard_normal(3)
            centre = positions[f, rng.choice(visible)] + direction / np.linalg.norm(direction) * rng.uniform(20, 300)
            alive.append((f + int(rng.integers(0, ghost_frames)), centre))
        alive = [(last, c) for last, c in alive if last >= f]
        ghost_pts = np.array([c for _, c in alive]).reshape(-1, 3) + rng.normal(0.0, 0.5, (len(alive), 3))
        cloud = np.concatenate([positions[f, visible], ghost_pts])
        owner = np.concatenate([visible, np.full(len(alive), -1)])
        order = rng.permutation(len(cloud))
        clouds.append(cloud[order])
        owners.append(owner[order])
    width = max((len(c) for c in clouds), default=0)
    points = np.full((n_frames, width, 3), np.nan)
    identity = np.full((n_frames, width), -1)
    for f, (cloud, owner) in enumerate(zip(clouds, owners, strict=True)):
        points[f, : len(cloud)] = cloud
        identity[f, : len(owner)] = owner
    return points, identity
