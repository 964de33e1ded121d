"""A learnt kinematic model of a hidden segment, fitted causally: where its markers sit in a visible neighbour's frame
as a function of how the other visible neighbours sit in that frame, regressed over a sliding window of past frames
(ridge regression), used only while the present configuration lies inside what was learnt (a Mahalanobis novelty
test); outside it the filler falls back to its rules (the segment placed through its joints)."""

from __future__ import annotations

import numpy as np


class PoseHistory:
    """The segments' poses (R, t) at the last ``length`` sampled frames, each marked known only where the segment
    was fitted to all its markers."""

    def __init__(self, segments: int, length: int) -> None:
        self.r = np.zeros((length, segments, 3, 3))
        self.t = np.zeros((length, segments, 3))
        self.ok = np.zeros((length, segments), dtype=bool)
        self.count = 0

    def add(self, r: np.ndarray, t: np.ndarray, ok: np.ndarray) -> None:
        row = self.count % len(self.r)
        self.r[row], self.t[row], self.ok[row] = r, t, ok
        self.count += 1

    def samples(self, segments: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """R (K, len(segments), 3, 3) and t (K, len(segments), 3) of the samples where all ``segments`` are known."""
        rows = self.ok[:, segments].all(axis=1)
        return self.r[rows][:, segments], self.t[rows][:, segments]


def relative(r: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(..., 12 (n - 1)) the poses of segments 1.. in the frame of segment 0: rotation entries and translation, from
    R (..., n, 3, 3) and t (..., n, 3)."""
    ref_r, ref_t = r[..., :1, :, :], t[..., :1, :]
    rot = np.swapaxes(ref_r, -1, -2) @ r[..., 1:, :, :]
    shift = (np.swapaxes(ref_r, -1, -2) @ (t[..., 1:, :] - ref_t)[..., None])[..., 0]
    return np.concatenate([rot.reshape(*rot.shape[:-2], 9), shift], axis=-1).reshape(*r.shape[:-3], -1)


class KinematicModel:
    """Ridge regression of ``targets`` (K, T) on ``features`` (K, D), with a novelty test on the features.

    Features are standardised over the window and the ridge penalty is ``ridge`` times the number of samples, so its
    strength does not depend on units or window length. A query is novel when its Mahalanobis distance to the window's
    features (covariance regularised by the same ridge) exceeds ``novelty`` times the largest distance of a sample
    of the window itself: outside the configurations learnt, a regression extrapolates and is not to be trusted.
    """

    def __init__(self, features: np.ndarray, targets: np.ndarray, ridge: float = 1e-3, novelty: float = 1.5) -> None:
        k, d = features.shape
        self.mean = features.mean(axis=0)
        self.scale = np.maximum(features.std(axis=0), 1e-9)
        x = (features - self.mean) / self.scale
        self.target_mean = targets.mean(axis=0)
        gram = x.T @ x + ridge * k * np.eye(d)
        self.weights = np.linalg.solve(gram, x.T @ (targets - self.target_mean))
        self.precision = np.linalg.inv(gram / k)
        self.limit = novelty * float(np.sqrt(np.einsum("kd,de,ke->k", x, self.precision, x).max()))

    def distance(self, features: np.ndarray) -> float:
        """Mahalanobis distance of one feature vector (D,) to the window's features."""
        x = (features - self.mean) / self.scale
        return float(np.sqrt(x @ self.precision @ x))

    def __call__(self, features: np.ndarray) -> np.ndarray | None:
        """The predicted targets (T,) for one feature vector (D,), or None when it is novel."""
        if not np.isfinite(features).all() or self.distance(features) > self.limit:
            return None
        return self.target_mean + ((features - self.mean) / self.scale) @ self.weights


class LearntPlacement:
    """The kinematic models of the hidden segments, asked for the segment's pose each frame: a hidden segment has
    one model per set of visible neighbours it has met since its gap began, each learnt from the pose history the
    first time the segment meets that set. The models are kept while the segment stays hidden, so neighbours seen
    and lost again and again (dropouts) cost one fit per set rather than one per change; they are dropped when the
    segment is seen again (``end_frame``) or nothing is hidden (``forget``).

    ``history`` takes the segments' poses at sampled frames; ``least`` samples are needed to learn a model.
    """

    def __init__(self, segments: int, length: int, least: int, novelty: float) -> None:
        self.history = PoseHistory(segments, length)
        self.least = least
        self.novelty = novelty
        self.models: dict[int, dict[tuple[int, ...], KinematicModel | None]] = {}  # per hidden segment, per
        # neighbour set (the reference first)
        self.asked: set[int] = set()  # segments whose model was asked for this frame

    def start_frame(self) -> None:
        self.asked = set()

    def end_frame(self) -> None:
        """Forget the models of the segments no longer hidden."""
        self.models = {k: model for k, model in self.models.items() if k in self.asked}

    def forget(self) -> None:
        self.models = {}

    def points(self, k: int, neighbours: list[int], reference: int | None, offsets: np.ndarray, r: np.ndarray,
               t: np.ndarray) -> np.ndarray | None:
        """(M, 3) the markers of the hidden segment ``k`` (at ``offsets`` in its frame) from the poses ``r``, ``t``
        of this frame's segments: its markers in the frame of one of its ``neighbours`` placed with their own
        markers (``reference`` when it is one of them) regressed on the others' poses in that frame. None: fewer
        than two such neighbours, too little history, or a configuration new to the model."""
        if len(neighbours) < 2:
            return None
        ref = reference if reference in neighbours else neighbours[0]
        order = [ref, *sorted(other for other in neighbours if other != ref)]
        key = tuple(order)
        self.asked.add(k)
        fits = self.models.setdefault(k, {})
        if key not in fits:
            fits[key] = self._learn(k, order, offsets)
        model = fits[key]
        predicted = None if model is None else model(relative(r[order], t[order]))
        return None if predicted is None else predicted.reshape(-1, 3) @ r[ref].T + t[ref]

    def _learn(self, k: int, order: list[int], offsets: np.ndarray) -> KinematicModel | None:
        """The model of segment ``k``'s markers (``offsets``) in the frame of ``order[0]`` on the poses of the other
        neighbours ``order[1:]``, from the samples where all were seen whole; None with too few of them."""
        past_r, past_t = self.history.samples([k, *order])
        if len(past_r) < max(self.least, 24 * (len(order) - 1)):  # 2 samples per feature
            return None
        world = offsets @ np.swapaxes(past_r[:, 0], 1, 2) + past_t[:, :1]  # (K, M, 3)
        local = (world - past_t[:, 1:2]) @ past_r[:, 1]  # in the reference's frame
        return KinematicModel(relative(past_r[:, 1:], past_t[:, 1:]), local.reshape(len(past_r), -1),
                              novelty=self.novelty)
