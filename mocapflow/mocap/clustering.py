"""Markers to segments: markers on one rigid segment keep their mutual distances, markers across a joint do not.

The clusterers work on the spread (standard deviation over time) of every pairwise marker distance:

- ``partition_rigidity`` (the default): markers that keep their distances within the recording's own noise, markers
  on the joints given to the segments that need them (which also reads the mean distances: a marker on a joint is
  its group's nearest to the other segment).
- ``cluster_spectral`` (Schoenauer 2007, 3.4): Gaussian affinity of the spreads with the local scaling of
  Zelnik-Manor and Perona (each marker's scale is its spread to its ``neighbour``-th nearest marker), normalised
  affinity ``D^-1/2 W D^-1/2``, its leading eigenvectors with rows normalised, and k-means on those rows. The
  number of segments, when not given, is where the eigenvalues drop most (the eigengap).
- ``cluster_distance_threshold`` (Aristidou 2008, 3.2): markers whose distance spreads stay under a threshold
  share a segment. ``linkage="complete"`` requires every pair of a segment to be under it (cliques);
  ``linkage="single"`` links through any chain of such pairs (connected components).

``SegmentTracker`` does the same on a live stream: running sums over a sliding window, O(N^2) vectorised work per
frame, and a new ``SegmentModel`` only when the partition changes.
"""

from __future__ import annotations

import os
import re
import warnings
from collections import Counter, deque
from collections.abc import Callable, Sequence
from typing import Any, Literal

import numpy as np
from scipy.cluster.hierarchy import fcluster
from scipy.cluster.hierarchy import linkage as hierarchy
from scipy.cluster.vq import kmeans2
from scipy.sparse.csgraph import connected_components
from scipy.spatial.distance import squareform

from mocapflow.mocap.markerset import added
from mocapflow.mocap.model import Segment, SegmentModel

MIN_PAIR_FRAMES = 10
"""Frames in which both markers of a pair must be visible for their distance spread to count."""
CLIP_SD = 10.0
"""A recording's pair distances further than this many standard deviations from their mean are left out of its pair
statistics (``pair_statistics``)."""
CLIP_PASSES = 2
"""How many times a recording's pair statistics are gathered again without the distances so far off."""
CLIP_MIN_MM = 1.0
"""A distance this close to its pair's mean is always kept (an exact rigid pair's spread is rounding error)."""


BODY_SPREAD_MM = 100.0
"""Two markers whose distance spreads more than this (mm) move on their own unless other markers link them. From one
segment to the next, some pair of the real captures' markers spreads by 22 mm at most; two subjects captured together
move apart by far more (two CMU subjects side by side: 174 mm at the least)."""


class PairStatistics:
    """Running count, sum and sum of squares of every pairwise marker distance (upper triangle, shifted sums).

    Each pair's distances are accumulated relative to the first distance seen for it, so that adding and removing
    thousands of frames does not lose the small variance of a rigid pair to cancellation.
    """

    def __init__(self, markers: int) -> None:
        self.markers = markers
        self.rows, self.cols = np.triu_indices(markers, 1)
        pairs = len(self.rows)
        self.count = np.zeros(pairs)
        self.total = np.zeros(pairs)
        self.squares = np.zeros(pairs)
        self.shift = np.full(pairs, np.nan)

    def grow(self, markers: int) -> np.ndarray:
        """Take on markers appended to the ``markers`` known, keeping every pair's sums; returns where the old pairs
        sit among the new ones (the new pairs start unseen)."""
        rows, cols = np.triu_indices(markers, 1)
        index = np.full((markers, markers), -1)
        index[rows, cols] = np.arange(len(rows))
        old = index[self.rows, self.cols]
        for name, empty in (("count", 0.0), ("total", 0.0), ("squares", 0.0), ("shift", np.nan)):
            grown = np.full(len(rows), empty)
            grown[old] = getattr(self, name)
            setattr(self, name, grown)
        self.markers, self.rows, self.cols = markers, rows, cols
        return old

    def distances(self, positions: np.ndarray) -> np.ndarray:
        """(B, P) pairwise distances of (B, N, 3) frames, NaN where a marker is missing."""
        diff = positions.take(self.rows, axis=1) - positions.take(self.cols, axis=1)
        return np.sqrt(np.einsum("bpi,bpi->bp", diff, diff))

    def add(self, distances: np.ndarray, sign: float = 1.0) -> None:
        """Add (``sign`` = 1) or remove (-1) the (B, P) distances of some frames."""
        seen = np.isfinite(distances)
        first = np.isnan(self.shift) & seen.any(0)  # pairs seen for the first time
        if first.any():
            self.shift[first] = distances[np.argmax(seen[:, first], axis=0), np.flatnonzero(first)]
        dev = np.where(seen, distances - self.shift, 0.0)  # a pair never seen has no shift yet and no distance
        self.count += sign * seen.sum(0)
        self.total += sign * dev.sum(0)
        self.squares += sign * (dev * dev).sum(0)

    def moments(self) -> tuple[np.ndarray, np.ndarray]:
        """Each pair's mean distance and its standard deviation (mm), in pair order (NaN mean for a pair never seen)."""
        n = np.maximum(self.count, 1)
        return self.shift + self.total / n, np.sqrt(np.maximum(self.squares / n - (self.total / n) ** 2, 0.0))

    def spread(self, min_frames: int = MIN_PAIR_FRAMES) -> np.ndarray:
        """(N, N) standard deviation of each pair's distance (mm); NaN for pairs seen together too rarely."""
        return self._square(np.where(self.count >= min_frames, self.moments()[1], np.nan))

    def mean(self, min_frames: int = MIN_PAIR_FRAMES) -> np.ndarray:
        """(N, N) mean of each pair's distance (mm); NaN for pairs seen together too rarely."""
        return self._square(np.where(self.count >= min_frames, self.moments()[0], np.nan))

    def _square(self, pairs: np.ndarray) -> np.ndarray:
        """The symmetric (N, N) matrix of per-pair values, zero on the diagonal."""
        out = np.zeros((self.markers, self.markers))
        out[self.rows, self.cols] = pairs
        out[self.cols, self.rows] = pairs
        return out


def pair_statistics(positions: np.ndarray, values: int = 4_000_000, clip: float = CLIP_SD,
                    passes: int = CLIP_PASSES) -> PairStatistics:
    """The distance statistics of every marker pair of (F, N, 3) trajectories, gathered in chunks of frames holding
    about ``values`` distances each, so memory stays bounded however many markers.

    A recording has the odd wrong sample: a ghost taken for a marker in one frame, two markers' points traded. One
    such sample 120 mm off among 3000 frames turns the 0.7 mm spread of a rigid pair into 2.5 mm, so that the pair no
    longer looks rigid. The statistics are therefore gathered again ``passes`` times, each time leaving out the
    distances more than ``clip`` standard deviations (of the pass before) from their pair's mean: a sample so far off
    is not the pair's motion, and of normally spread distances it leaves out one in 15,000 (never one within
    ``CLIP_MIN_MM`` of the mean)."""
    positions = np.asarray(positions, dtype=np.float64)
    markers = positions.shape[1]
    chunk = max(1, values // max(markers * (markers - 1) // 2, 1))
    bounds: tuple[np.ndarray, np.ndarray] | None = None  # each pair's mean and the farthest kept from it
    for _ in range(passes + 1):
        stats = PairStatistics(markers)
        for start in range(0, positions.shape[0], chunk):
            distances = stats.distances(positions[start:start + chunk])
            if bounds is not None:
                with np.errstate(invalid="ignore"):
                    distances[np.abs(distances - bounds[0]) > bounds[1]] = np.nan
            stats.add(distances)
        mean, sd = stats.moments()
        bounds = (mean, np.maximum(clip * sd, CLIP_MIN_MM))
    return stats


def distance_spread(positions: np.ndarray, min_frames: int = MIN_PAIR_FRAMES, values: int = 4_000_000,
                    clip: float = CLIP_SD) -> np.ndarray:
    """(N, N) standard deviation over time of every pairwise marker distance of (F, N, 3) trajectories (mm), without
    the distances far off their pair's mean (``pair_statistics``)."""
    return pair_statistics(positions, values, clip).spread(min_frames)


def _groups(assignment: np.ndarray) -> list[list[int]]:
    """Marker indices per cluster, clusters ordered by their first marker."""
    groups: dict[int, list[int]] = {}
    for marker, cluster in enumerate(assignment):
        groups.setdefault(int(cluster), []).append(marker)
    return sorted(groups.values(), key=lambda g: g[0])


def _unseen_as_far(spread: np.ndarray) -> np.ndarray:
    """Pairs never seen together count as far apart as the farthest pair seen (they share no evidence)."""
    far = np.nanmax(spread) if np.isfinite(spread).any() else 1.0
    return np.where(np.isfinite(spread), spread, max(far, 1.0))


def spectral_embedding(spread: np.ndarray, neighbour: int = 3,
                       floor_mm: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues (descending) and eigenvectors of the locally scaled, normalised affinity of a spread matrix."""
    d = _unseen_as_far(spread)
    n = d.shape[0]
    ranked = np.sort(d + np.diag(np.full(n, np.inf)), axis=1)
    sigma = np.maximum(ranked[:, min(neighbour, n - 1) - 1], floor_mm)
    w = np.exp(-(d * d) / np.outer(sigma, sigma))
    np.fill_diagonal(w, 0.0)
    inv = 1.0 / np.sqrt(np.maximum(w.sum(1), 1e-300))
    values, vectors = np.linalg.eigh(inv[:, None] * w * inv[None, :])
    return values[::-1], vectors[:, ::-1]


def eigengap_k(values: np.ndarray, k_max: int | None = None) -> int:
    """Number of clusters where consecutive eigenvalues (descending) drop most."""
    k_max = len(values) - 1 if k_max is None else min(k_max, len(values) - 1)
    if k_max < 1:
        return 1
    return int(np.argmax(values[:k_max] - values[1:k_max + 1])) + 1


def partition_spectral(spread: np.ndarray, k: int | None = None, *, neighbour: int = 3, restarts: int = 10,
                       seed: int = 0) -> list[list[int]]:
    """Spectral clustering of a spread matrix (see ``cluster_spectral``)."""
    n = spread.shape[0]
    if n == 0:
        return []
    if n == 1:
        return [[0]]
    values, vectors = spectral_embedding(spread, neighbour)
    k = eigengap_k(values) if k is None else int(k)
    if not 1 <= k <= n:
        raise ValueError(f"cannot make {k} segments from {n} markers")
    if k == 1:
        return [list(range(n))]
    x = vectors[:, :k]
    y = x / np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-300)
    rng = np.random.default_rng(seed)
    best, best_cost = None, np.inf
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # an empty cluster in one restart is simply a worse restart
        for _ in range(restarts):
            centres, labels = kmeans2(y, k, minit="++", rng=rng, check_finite=False)  # unit rows: finite
            if len(np.unique(labels)) < k:
                continue
            cost = float(((y - centres[labels]) ** 2).sum())
            if cost < best_cost - 1e-12:
                best, best_cost = labels, cost
    if best is None:
        raise ValueError(f"k-means found no {k} non-empty clusters")
    return _groups(best)


def partition_threshold(spread: np.ndarray, k: int | None = None, *, threshold_mm: float = 5.0,
                        linkage: Literal["complete", "single"] = "complete") -> list[list[int]]:
    """Threshold clustering of a spread matrix (see ``cluster_distance_threshold``)."""
    n = spread.shape[0]
    if n <= 1:
        return [list(range(n))]
    tree = hierarchy(squareform(_unseen_as_far(spread), checks=False), method=linkage)
    if k is None:
        labels = fcluster(tree, t=threshold_mm, criterion="distance")
    else:
        labels = fcluster(tree, t=int(k), criterion="maxclust")
    return _groups(labels)


def cluster_spectral(positions: np.ndarray, k: int | None = None, *, neighbour: int = 3, restarts: int = 10,
                     seed: int = 0) -> list[list[int]]:
    """Segments of (F, N, 3) trajectories by spectral clustering (Schoenauer 3.4.2 with Zelnik-Manor-Perona scaling).

    ``k`` segments, or as many as the eigengap says. ``neighbour`` picks the local scale (small: segments have few
    markers); k-means is restarted ``restarts`` times from seeded k-means++ starts and the tightest result kept.
    Returns marker indices per segment.
    """
    return partition_spectral(distance_spread(positions), k, neighbour=neighbour, restarts=restarts, seed=seed)


def cluster_distance_threshold(positions: np.ndarray, k: int | None = None, *, threshold_mm: float = 5.0,
                               linkage: Literal["complete", "single"] = "complete") -> list[list[int]]:
    """Segments of (F, N, 3) trajectories: markers whose distance spreads stay under ``threshold_mm`` (Aristidou 3.2).

    With ``k`` given, the threshold is the one that yields exactly ``k`` segments (Schoenauer 3.4.1). Returns marker
    indices per segment.
    """
    return partition_threshold(distance_spread(positions), k, threshold_mm=threshold_mm, linkage=linkage)


def bodies(spread: np.ndarray, limit: float = BODY_SPREAD_MM) -> np.ndarray:
    """(N,) which independently moving body each marker belongs to, numbered from 0 in order of first marker: markers
    linked by a chain of pairs whose distances spread less than ``limit`` (two subjects, or a subject and a prop)."""
    linked = np.isfinite(spread) & (spread < limit)
    _, body = connected_components(linked, directed=False)
    _, first = np.unique(body, return_index=True)
    order = np.argsort(np.argsort(first))  # bodies renumbered by their first marker
    return np.asarray(order[body], dtype=np.intp)


def noise_floor(spread: np.ndarray) -> float:
    """A recording's rigidity noise (mm): the upper quartile, over markers, of the spread to their most rigid partner.

    Nearly every marker shares a segment with another, so this is how much the distance of a rigid pair varies in
    this recording (skin and soft tissue, the tracker's noise), read where it is typical rather than best.
    """
    d = np.where(np.isfinite(spread), spread, np.inf)
    np.fill_diagonal(d, np.inf)
    nearest = d.min(1)
    nearest = nearest[np.isfinite(nearest)]
    return float(np.percentile(nearest, 75)) if len(nearest) else 1.0


def partition_rigidity(spread: np.ndarray, k: int | None = None, *, distance: np.ndarray, factor: float = 3.0,
                       bridge: float = 2.0, loose: float = 3.0, floor_mm: float = 0.1) -> list[list[int]]:
    """Segments as the markers that keep their distances within the recording's own noise; ``distance`` holds the
    mean of every pairwise distance (mm), as ``spread`` their standard deviation.

    1. Markers are grouped so that every two of a group are rigid: complete linkage cut at ``factor`` times the
       noise floor (``noise_floor``, at least ``floor_mm``).
    2. A marker left alone may be on a segment whose other markers sit on its joints (a thigh marker whose knee
       marker went to the shank). When its most rigid partner is rigid with it but not with its own group-mates
       (their spreads to the lone marker are over ``bridge`` times larger), and the group stays rigid without it,
       that partner is a joint marker: the lone marker takes it, provided its group keeps two markers, or its
       group's other marker can take its own most rigid partner in turn (a knee marker to the thigh, the ankle
       marker to the shank). A marker on the joint between two segments is, of its group, the one nearest the
       other segment: the marker taking one in turn takes only the member of that group nearest to it (a thigh
       marker robbed of its knee marker does not take a back marker that happened to keep still with it).
    3. Otherwise it joins the group it is most rigid with when that group's spreads to it stay under ``loose``
       times the threshold (a soft segment: shoulder markers on the trunk); a marker rigid with nothing stays
       alone.

    Markers of bodies that move on their own (``bodies``: two subjects captured together) are grouped body by body,
    each at its own noise floor. With ``k`` given, complete linkage cut at ``k`` groups.
    """
    n = spread.shape[0]
    if n <= 2 or k is not None:
        return partition_threshold(spread, k, threshold_mm=np.inf, linkage="complete") if n > 1 else [[0]] * n
    body = bodies(spread)
    if body.max() > 0:  # each body at its own noise: two subjects' skin moves differently
        groups = []
        for b in range(body.max() + 1):
            own = np.flatnonzero(body == b)
            part = partition_rigidity(spread[np.ix_(own, own)], distance=distance[np.ix_(own, own)], factor=factor,
                                      bridge=bridge, loose=loose, floor_mm=floor_mm)
            groups += [[int(own[m]) for m in g] for g in part]
        return sorted((sorted(g) for g in groups), key=lambda g: g[0])
    d = _unseen_as_far(spread)
    near = np.where(np.isfinite(distance), distance, np.inf)  # pairs never seen together: as far as can be
    threshold = factor * max(noise_floor(spread), floor_mm)
    groups = partition_threshold(spread, threshold_mm=threshold, linkage="complete")

    def group_of(m: int) -> list[int]:
        return next(g for g in groups if m in g)

    def partner(m: int, test: bool) -> int | None:
        """m's most rigid marker outside its group; with ``test``, only when its group-mates are not rigid with m."""
        own = group_of(m)
        j = min((x for x in range(n) if x not in own), key=lambda x: d[m, x])
        mates = [x for x in group_of(j) if x != j]
        return j if not test or (mates and d[m, mates].min() > bridge * d[m, j]) else None

    def takes(m: int, cascade: bool) -> list[int] | None:
        """The joint markers that m, and in turn the one it leaves alone, take (None: no such move)."""
        j = partner(m, test=not cascade)
        if j is None:
            return None
        donor = group_of(j)
        rest = [x for x in donor if x != j]
        if cascade and rest and near[m, j] > near[m, rest].min():
            return None  # in turn, only the marker of its group nearest m: the one on their joint
        if len(rest) > 1 and d[np.ix_(rest, rest)].max() > threshold:
            return None  # taking j would leave its group no longer rigid: j is not a joint marker of it
        if len(donor) >= 3:
            return [j]
        if len(donor) == 2 and not cascade:
            left = donor[0] if donor[1] == j else donor[1]
            more = takes(left, cascade=True)
            return [j, *more] if more else None
        return None

    changed = True
    while changed:
        changed = False
        for alone in [g for g in groups if len(g) == 1]:
            chain = takes(alone[0], cascade=False)
            if chain:
                taker = alone
                for j in chain:
                    donor = group_of(j)
                    donor.remove(j)
                    taker.append(j)
                    taker = donor
                changed = True
                break
            spreads = [(d[alone[0], g].max(), i) for i, g in enumerate(groups) if len(g) >= 2]
            if spreads and min(spreads)[0] <= loose * threshold:
                groups[min(spreads)[1]].append(alone.pop())
                groups.remove(alone)
                changed = True
                break
    return sorted((sorted(g) for g in groups), key=lambda g: g[0])


PARTITIONERS: dict[str, Callable[..., list[list[int]]]] = {
    "rigidity": partition_rigidity,
    "spectral": partition_spectral,
    "distance-threshold": partition_threshold,
}
"""Clustering methods by name, each taking a spread matrix and ``k`` (``partition`` calls them)."""


def known_method(method: str) -> str:
    """``method`` when it names a clustering method (``PARTITIONERS``); a ValueError naming them otherwise."""
    if method not in PARTITIONERS:
        raise ValueError(f"unknown clustering method {method!r}; choose one of {', '.join(PARTITIONERS)}")
    return method


def partition(method: str, stats: PairStatistics, k: int | None = None, min_frames: int = MIN_PAIR_FRAMES,
              **options: object) -> list[list[int]]:
    """Markers to segments by clustering ``method`` (``PARTITIONERS``) from a recording's pair statistics (the
    rigidity clusterer also reads the mean distances); ``options`` go to the clusterer."""
    known_method(method)
    if method == "rigidity":
        options = {"distance": stats.mean(min_frames), **options}
    return PARTITIONERS[method](stats.spread(min_frames), k, **options)


_BODY_WORDS: tuple[tuple[str, str], ...] = (  # (pattern on a label without its side letter, body part)
    (r"SH[N0-9]|TIB|TB\d|TI[A-Z]|SHIN", "shank"), (r"TH|FEM", "thigh"),
    (r"HEE|TOE|MT\d|P\dMT|CAL|MF[SL]|CUN|FOOT", "foot"), (r"UPA|UA\d|ARM|HUM", "upper_arm"),
    (r"FRM|FA|FOREARM|WR|RAD|ULN", "forearm"), (r"FIN|HN\d|HAND|MCP", "hand"),
    (r"KNE|KN|ANK|ELB|[LM]EPI|PAT|[LM]?MAL|[LM]AK|[LM]EL", ""),  # on a joint: says nothing of the segment
    (r"ASI|PSI|[FB]?WT|SACR?$|PELV|P\d$", "pelvis"), (r"[FB]?HD|HEAD|HED", "head"),
    (r"C7|T\d|CLAV|STR?N|STER|BA[CK]|SHO|SHL|SH$|ACR|MAN|XIPH", "trunk"),
)
_SIDES = {"L": "left", "R": "right"}


def _body_word(label: str) -> tuple[str | None, str | None]:
    """(side, body part) a marker label names, e.g. ``LTHI`` -> (left, thigh), ``C7`` -> (None, trunk); a part of
    None when the label says nothing, "" for a marker on a joint."""
    name = label.rpartition(":")[2].upper()
    for rest, side in ((name[1:], _SIDES.get(name[:1])), (name, None)):
        if rest and (side or rest is name):
            for pattern, word in _BODY_WORDS:
                if re.match(pattern, rest):
                    return side, word
    return None, None


def segment_names(groups: Sequence[Sequence[int]], labels: Sequence[str]) -> list[str]:
    """A readable, unique name per segment: its markers' common label prefix (``LTH1..LTH4`` -> ``LTH``) when that
    is at least two characters, else the body part its labels name (``LTHI, LKNE`` -> ``left_thigh``, ``C7, CLAV``
    -> ``trunk``, by majority, markers on joints not voting), else ``segment<i>``; a repeated name is numbered."""
    names = []
    for i, group in enumerate(groups):
        short = [labels[m].rpartition(":")[2] for m in group]
        prefix = os.path.commonprefix(short).rstrip("_-: ") if len(group) > 1 else ""
        if len(prefix) >= 2:
            names.append(prefix)
            continue
        votes = [_body_word(labels[m]) for m in group]
        words = Counter(word for _, word in votes if word)
        word = words.most_common(1)[0][0] if words else ""
        sides = {side for side, w in votes if w == word}
        if word in ("pelvis", "head", "trunk") or not word:
            names.append(word or f"segment{i}")
        else:
            names.append(f"{sides.pop()}_{word}" if len(sides) == 1 and None not in sides else f"segment{i}")
    counts = Counter(names)
    seen: Counter[str] = Counter()
    unique = []
    for name in names:
        seen[name] += 1
        unique.append(name if counts[name] == 1 else f"{name}_{seen[name]}")
    return unique


def segment_model(groups: Sequence[Sequence[int]], labels: Sequence[str]) -> SegmentModel:
    """The ``SegmentModel`` of a partition given as marker indices."""
    names = segment_names(groups, labels)
    return SegmentModel(segments=[Segment(name=name, markers=[labels[m] for m in group])
                                  for name, group in zip(names, groups, strict=True)])


class SegmentTracker:
    """Streaming clusterer: distance spreads over a sliding window, re-clustered every ``every`` frames.

    ``update`` returns a ``SegmentModel`` after the warm-up (``warmup`` frames, default one window) whenever the
    partition differs from the last one returned, else None. While the partition holds, the interval between two
    clusterings doubles, up to ``backoff`` times ``every``; a change brings it back to ``every``. ``options`` go to
    the partitioner (``k``, ``neighbour``, ``threshold_mm``...).
    """

    def __init__(self, labels: Sequence[str], *, window: int = 600, warmup: int | None = None, every: int = 30,
                 backoff: int = 4, method: Literal["rigidity", "spectral", "distance-threshold"] = "spectral",
                 **options: Any) -> None:
        self.method = known_method(method)
        self.labels = list(labels)
        self.window = window
        self.warmup = window if warmup is None else warmup
        self.every = every
        self.backoff = backoff
        self.interval = every
        self.next = self.warmup
        self.options = options
        self.stats = PairStatistics(len(self.labels))
        self.history: deque[np.ndarray] = deque()
        self.frames = 0
        self.current: list[list[int]] | None = None

    def grow(self, labels: Sequence[str]) -> None:
        """Take on the markers appended to the labels (``markerset``), keeping the window of distances seen so far;
        the next clustering places them."""
        new = added(self.labels, labels)
        if new is None:
            raise ValueError("the labels do not extend the tracker's: a new marker set needs a new tracker")
        if not new:
            return
        old = self.stats.grow(len(labels))
        pairs = len(self.stats.rows)

        def widen(d: np.ndarray) -> np.ndarray:
            out = np.full((len(d), pairs), np.nan)
            out[:, old] = d
            return out

        self.history = deque(widen(d) for d in self.history)
        self.labels = list(labels)

    def update(self, frame_positions: np.ndarray) -> SegmentModel | None:
        """Add one (N, 3) frame (NaN for missing markers)."""
        d = self.stats.distances(np.asarray(frame_positions, dtype=np.float64)[None])
        self.stats.add(d)
        self.history.append(d)
        if len(self.history) > self.window:
            self.stats.add(self.history.popleft(), -1.0)
        self.frames += 1
        if self.frames < self.next:
            return None
        groups = partition(self.method, self.stats, **self.options)
        unchanged = groups == self.current
        self.interval = min(2 * self.interval, self.backoff * self.every) if unchanged else self.every
        self.next = self.frames + self.interval
        if unchanged:
            return None
        self.current = groups
        return segment_model(groups, self.labels)
