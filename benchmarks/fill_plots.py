"""True against filled trajectories through a 3 s gap on the real lower-body recording, one picture per occlusion
case: docs/img/fill-<case>.png.

Run: python benchmarks/fill_plots.py [--seed N]. The cases, the markers hidden and the filler runs are those of
benchmarks/fill_accuracy.py (method ``skeleton``, with linear interpolation across the gap for comparison, which sees
the frames after the gap, and, but for the one-camera case, the same filler offline, both ways through the file).
Each picture shows x, y and z of the first hidden marker against time, and below them the distance of each estimate
from the truth on a log scale.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import fill_accuracy as fa  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from mocapflow.mocap.filling import FillerConfig, fill_both_ways  # noqa: E402

OUT = Path(__file__).resolve().parents[1] / "docs" / "img"
FILE = "lowerbody_clusters_knee_0401.c3d"
SHORT = {"one missing": "one-missing", "two missing": "two-missing", "all missing": "all-missing",
         "one on each of two segments": "two-segments", "one-camera, one on each": "one-camera"}


def plot_case(ds: fa.Dataset, case: str, rng: np.random.Generator, path: Path) -> float:
    """Hide markers for ``case`` over one 3 s gap, fill, and draw the first hidden marker; the filler's mean error."""
    gap = round(fa.GAP_S * ds.rate)
    margin = round(ds.rate)
    names, _ = fa.pick(ds, case, rng)
    hidden = [ds.labels.index(m) for m in names]
    start = int(rng.integers(margin, len(ds.observed) - gap - margin))
    stop = start + gap
    x = ds.observed.copy()
    x[start:stop, hidden] = np.nan
    rays = fa.single_cameras(ds, len(hidden), rng) if case.startswith("one-camera") else None
    filled, _ = fa.run_filler(ds, x, start, stop, hidden, rays, FillerConfig(), ds.skeleton)
    linear = fa.interpolate(x, start, stop, hidden, "linear", ds.rate)
    both = None if rays is not None else fill_both_ways(x, ds.labels, ds.rate, FillerConfig(), ds.skeleton).positions[
        start:stop]
    m = hidden[0]
    t = np.arange(start - margin, stop + margin) / ds.rate
    tg = np.arange(start, stop) / ds.rate
    truth = ds.truth[start:stop, m]
    err_fill = np.linalg.norm(filled[:, m] - truth, axis=1)
    err_lin = np.linalg.norm(linear[:, m] - truth, axis=1)

    fig, axes = plt.subplots(4, 1, figsize=(8, 8.5), sharex=True, gridspec_kw={"height_ratios": [1, 1, 1, 1.1]})
    for axis, ax in enumerate(axes[:3]):
        ax.axvspan(tg[0], tg[-1], color="0.92", lw=0)
        ax.plot(t, ds.truth[start - margin:stop + margin, m, axis], color="k", lw=2.2, label="true (deleted)")
        ax.plot(tg, linear[:, m, axis], color="tab:orange", lw=1.4, ls="--", label="linear interpolation")
        ax.plot(tg, filled[:, m, axis], color="tab:blue", lw=1.4, label="filled (skeleton)")
        if both is not None:
            ax.plot(tg, both[:, m, axis], color="tab:green", lw=1.2, ls=":", label="offline (both ways)")
        ax.set_ylabel(f"{'xyz'[axis]} (mm)")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper left", fontsize=8, ncol=4, framealpha=0.9)
    ax = axes[3]
    ax.axvspan(tg[0], tg[-1], color="0.92", lw=0)
    ax.semilogy(tg, np.maximum(err_lin, 1e-2), color="tab:orange", lw=1.4, ls="--",
                label=f"linear, mean {err_lin.mean():.1f} mm")
    ax.semilogy(tg, np.maximum(err_fill, 1e-2), color="tab:blue", lw=1.4,
                label=f"filled, mean {err_fill.mean():.2f} mm")
    if both is not None:
        err_both = np.linalg.norm(both[:, m] - truth, axis=1)
        ax.semilogy(tg, np.maximum(err_both, 1e-2), color="tab:green", lw=1.2, ls=":",
                    label=f"offline, mean {err_both.mean():.2f} mm")
    ax.set_ylabel("error (mm)")
    ax.set_xlabel("time (s)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(loc="upper left", fontsize=8, ncol=3, framealpha=0.9)
    hidden_text = ", ".join(names) + (" (single-camera rays)" if rays is not None else "")
    fig.suptitle(f"{case}: {names[0]} through a {fa.GAP_S:g} s gap (grey); hidden {hidden_text}", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return float(err_fill.mean())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seed", type=int, default=3)
    args = parser.parse_args()
    ds = fa.real(FILE, fa.LOWER_BODY, None)
    if ds is None:
        print(f"{FILE} absent: nothing drawn")
        return
    OUT.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(args.seed)
    for case in fa.CASES:
        path = OUT / f"fill-{SHORT[case]}.png"
        error = plot_case(ds, case, rng, path)
        print(f"{case:<30} {error:7.2f} mm  {path.relative_to(OUT.parents[1])} ({path.stat().st_size // 1024} KB)")


if __name__ == "__main__":
    main()
