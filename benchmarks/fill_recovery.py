"""Gap filling on the MocapRecovery protocol (Tits, Tilmanne & Dutoit, PLoS ONE 2018) against the methods of the
literature: mocapflow causal and offline next to Burke & Lasenby's low-dimensional Kalman smoother, Gløersen &
Federolf's PCA reconstruction, and linear and spline interpolation.

Run: python benchmarks/fill_recovery.py [--runs N] [--gap 2 --gap 0.5] [--file NAME] [--plot PNG]. Per CMU
recording of the shared data folder and gap length, each run deletes, in 5 markers drawn at random, 1 to 10 gaps each
(drawn at random, starting anywhere, frame 0 included; gaps of a marker may overlap), fills the recording with every
method, and scores the mean distance (mm) between the filled and the deleted samples; samples a method leaves unfilled
are counted apart (``unfilled``) and left out of its mean.

mocapflow runs with a skeleton calibrated (``mocapflow calibrate``) on the recording with its gaps, as a user would
have it: ``causal`` is the live filler frame by frame, ``offline`` the same filler both ways (``fill --offline``).
The reference methods are in benchmarks/gap_methods.py.
"""

from __future__ import annotations

import argparse
import time

import _common
import numpy as np
from gap_methods import interpolate, kalman_smoother_fill, pca_fill

from mocapflow.errors import CalibrationError
from mocapflow.io.markers import read_markers
from mocapflow.mocap.calibration import calibrate
from mocapflow.mocap.filling import fill_both_ways, fill_recording

FILES = ("cmu_85_02.c3d", "cmu_dribble_shoot_basketball.c3d", "cmu_02_05.c3d", "cmu_85_12_breakdance.c3d")
METHODS = ("causal", "offline", "burke", "pca", "linear", "spline")


def corrupt(x: np.ndarray, rate: float, gap_s: float, rng: np.random.Generator) -> np.ndarray:
    """The protocol's gaps: 5 random markers, each with 1-10 gaps of ``gap_s`` starting anywhere (frame 0 too)."""
    out = x.copy()
    length = round(gap_s * rate)
    for m in rng.choice(x.shape[1], 5, replace=False):
        for start in rng.integers(0, len(x) - length + 1, rng.integers(1, 11)):
            out[start:start + length, m] = np.nan
    return out


def fill_all(x: np.ndarray, labels: list[str], rate: float) -> dict[str, np.ndarray]:
    """Every method's filled recording, and the CPU seconds each took (printed)."""
    out: dict[str, np.ndarray] = {}
    seconds: dict[str, float] = {}
    try:
        (skeleton, cal_s) = _common.timed(calibrate, x, labels, rate)
    except CalibrationError:
        skeleton, cal_s = None, 0.0
    for name, run in (("causal", lambda: fill_recording(x, labels, rate, None, skeleton).positions),
                      ("offline", lambda: fill_both_ways(x, labels, rate, None, skeleton).positions),
                      ("burke", lambda: kalman_smoother_fill(x, rate)), ("pca", lambda: pca_fill(x)),
                      ("linear", lambda: interpolate(x, "linear")), ("spline", lambda: interpolate(x, "spline"))):
        out[name], seconds[name] = _common.timed(run)
    print(f"    cpu s: calibrate {cal_s:.1f}, " + ", ".join(f"{k} {v:.1f}" for k, v in seconds.items()),
          flush=True)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=3, help="corrupted copies per file and gap length (default 3)")
    parser.add_argument("--gap", type=float, action="append", help="gap length in s (repeatable; default 2 and 0.5)")
    parser.add_argument("--file", choices=FILES, action="append", help="only this file (repeatable)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--plot", help="also draw the table as bars (log scale) into this PNG")
    args = parser.parse_args()
    start = time.perf_counter()
    rows = []
    for file in args.file or FILES:
        path = _common.DATA / file
        if not path.is_file():
            print(f"({path} absent: skipped)")
            continue
        data = read_markers(path)
        truth = data.positions
        for gap_s in args.gap or (2.0, 0.5):
            rng = np.random.default_rng([args.seed, FILES.index(file), round(gap_s * 1000)])
            errors: dict[str, list[float]] = {m: [] for m in METHODS}
            unfilled = dict.fromkeys(METHODS, 0)
            deleted = 0
            for run in range(args.runs):
                x = corrupt(truth, data.rate, gap_s, rng)
                hole = ~np.isfinite(x).all(-1) & np.isfinite(truth).all(-1)
                deleted += int(hole.sum())
                print(f"  {file} {gap_s:g} s run {run + 1}: {int(hole.sum())} samples deleted", flush=True)
                for method, filled in fill_all(x, data.labels, data.rate).items():
                    error = np.linalg.norm(filled[hole] - truth[hole], axis=-1)
                    unfilled[method] += int(np.isnan(error).sum())
                    errors[method].extend(error[np.isfinite(error)].tolist())
            rows.append((file, gap_s, deleted, {m: (float(np.mean(errors[m])) if errors[m] else np.nan, unfilled[m])
                                                for m in METHODS}))
    print(f"\nMocapRecovery protocol, {args.runs} runs per file and gap: mean error mm (unfilled samples)")
    print(f"{'file':<34}{'gap s':>6}{'deleted':>9}" + "".join(f"{m:>16}" for m in METHODS))
    for file, gap_s, deleted, scores in rows:
        print(f"{file:<34}{gap_s:>6g}{deleted:>9}" + "".join(
            f"{f'{e:.1f} ({u})':>16}" for e, u in (scores[m] for m in METHODS)))
    print(f"({time.perf_counter() - start:.0f} s wall)")
    if args.plot:
        plot(rows, args.plot)


def plot(rows: list[tuple[str, float, int, dict[str, tuple[float, int]]]], path: str) -> None:
    """Mean error per method, one group of bars per file and gap length, log scale."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(11, 4.2))
    width = 0.8 / len(METHODS)
    for k, method in enumerate(METHODS):
        ax.bar(np.arange(len(rows)) + (k - (len(METHODS) - 1) / 2) * width, [r[3][method][0] for r in rows], width,
               label="causal (filled samples only)" if method == "causal" else method)
    names = [r[0].removeprefix("cmu_").removesuffix(".c3d").replace("_shoot_basketball", "") for r in rows]
    ax.set_xticks(np.arange(len(rows)), [f"{name}\n{r[1]:g} s gaps" for name, r in zip(names, rows, strict=True)],
                  fontsize=8)
    ax.set_yscale("log")
    ax.set_ylabel("mean error of the deleted samples (mm)")
    ax.set_title("MocapRecovery protocol (5 markers, 1-10 gaps each) on the CMU recordings")
    ax.legend(ncol=len(METHODS), fontsize=7)
    ax.grid(axis="y", which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    main()
