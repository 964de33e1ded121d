"""Who holds each marker, frame by frame, under the labelling benchmark's stress damage: docs/img/labelling-stress.png.

Run: python benchmarks/labelling_figure.py [--capture NAME] [--seed N] [--data DIR]. The capture (default the real
cmu_85_02.c3d, whole) is damaged as the stress cases of benchmarks/labelling.py are (each marker hidden a third of the
time in gaps of 0.2-2 s, one-frame ghosts, the points shuffled) and labelled without a model, streaming as the live
``labeller`` node does and offline as ``mocapflow label`` does. One row per true marker, one column per frame: hidden,
on the track that stands for it (the track holding most of its points), on another track of its own (a fragment), on
another marker's track (wrong), or seen and on no track (unlabelled: streaming waits ``confirm_frames`` before it
names a point it could not re-identify at once).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import _common  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from labelling import stream_labels  # noqa: E402
from matplotlib.colors import ListedColormap  # noqa: E402
from matplotlib.patches import Patch  # noqa: E402

from mocapflow.io.markers import read_markers  # noqa: E402
from mocapflow.mocap.evaluation import STRESS, held_markers, score_labelling, track_markers, unlabel  # noqa: E402
from mocapflow.mocap.labelling import label_sequence  # noqa: E402

OUT = Path(__file__).resolve().parents[1] / "docs" / "img" / "labelling-stress.png"
STATES = (("hidden", "#ececec"), ("on its own track", "#7fbf7b"), ("on a fragment of its own", "#5b8fd6"),
          ("on another marker's track", "#d62728"), ("seen, unlabelled", "#ff9f1c"))


def states(tracks: np.ndarray, points: list[np.ndarray], identity: list[np.ndarray], markers: int) -> np.ndarray:
    """Per frame and true marker, the index of its state in ``STATES``."""
    held, seen, _ = held_markers(tracks, points, identity, markers)
    stands = track_markers(held, markers)
    own = np.full(markers, -1)  # per marker, the track that stands for it: of those standing for it, the fullest
    for m in range(markers):
        mine = np.flatnonzero(stands == m)
        if len(mine):
            own[m] = mine[np.argmax((held[:, mine] == m).sum(axis=0))]
    out = np.where(seen, 4, 0)
    frames, tracks_on = np.nonzero(held >= 0)
    marker = held[frames, tracks_on]
    out[frames, marker] = np.where(tracks_on == own[marker], 1, np.where(stands[tracks_on] == marker, 2, 3))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--capture", default="cmu_85_02.c3d", help="a labelled capture of the data folder")
    parser.add_argument("--seed", type=int, default=1, help="the damage's seed (default 1, the benchmark's)")
    parser.add_argument("--data", type=Path, default=_common.DATA, help="folder of the real captures")
    args = parser.parse_args()
    data = read_markers(args.data / args.capture)
    rate, markers = data.rate, len(data.labels)
    points, identity = unlabel(data.positions, rate, seed=args.seed, stationary=True, **STRESS)
    points, identity = list(points), list(identity)
    streamed, _ = stream_labels(points, rate)
    offline, _ = label_sequence(points, rate)
    fig, axes = plt.subplots(2, 1, figsize=(12, 9.5), sharex=True)
    for ax, (how, tracks) in zip(axes, (("streaming (live)", streamed), ("offline (mocapflow label)", offline)),
                                 strict=True):
        score = score_labelling(tracks, points, identity, markers)
        shown = states(tracks, points, identity, markers)
        ax.imshow(shown.T, aspect="auto", interpolation="nearest", cmap=ListedColormap([c for _, c in STATES]),
                  vmin=-0.5, vmax=len(STATES) - 0.5, extent=(0, len(points) / rate, markers - 0.5, -0.5))
        ax.set_yticks(range(markers), data.labels, fontsize=6)
        ax.set_title(f"{how}: {100 * score.accuracy:.2f} % of true points on a track of their own marker, "
                     f"{score.swaps} swaps, {score.tracks} tracks for {markers} markers", fontsize=10)
        print(f"{how}: {100 * score.accuracy:.3f} % right, {score.swaps} swaps, {score.tracks} tracks, "
              f"{100 * (1 - score.assigned):.3f} % of true points unlabelled")
    axes[-1].set_xlabel("time (s)")
    fig.legend(handles=[Patch(color=c, label=label) for label, c in STATES], loc="lower center", ncol=len(STATES),
               fontsize=9, frameon=False)
    fig.suptitle(f"{args.capture} ({rate:g} Hz), each marker hidden a third of the time, one-frame ghosts in a fifth "
                 f"of the frames (seed {args.seed})", fontsize=11)
    fig.tight_layout(rect=(0, 0.04, 1, 0.97))
    OUT.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(OUT, dpi=110)
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
