"""Occlusion filling accuracy for gaps of 3 s, by occlusion case, against interpolation and a Kalman-only filler.

Run: python benchmarks/fill_accuracy.py [--runs N]. Markers are deleted from complete data over 3 s gaps placed at
random, filled, and compared with what was deleted (real files) or with the noise-free truth (simulator). The table
gives the mean distance (mm) between filled and true markers over the gap frames, and after the slash the mean
distance between the estimated and reference joint centres of the joints next to the hidden markers (for the real
files the reference is the joint as placed from the complete data with the same skeleton).

Methods: ``skeleton`` is the filler with a calibrated skeleton (simulator: the true one; real files:
``calibration.build_skeleton`` on the complete recording, as from a calibration trial); ``thesis`` the same with the
thesis's own choices (centres of rotation only for a fully hidden segment, constant rotor, rays by projection only);
``learned`` the filler with no skeleton, learning it from the frames seen (only where the gap starts late enough);
``kalman`` each marker's own filter; ``linear`` and ``spline`` interpolate across the gap with the frames after it,
which no real-time method can see. The joint centres of kalman, linear and spline come from the same skeleton fitted
to their filled markers (the mean of both sides, Aristidou eq. 4.29).

Thesis (Aristidou 2008, real data, tables 6.1-6.4): one missing 2.58 mm (CoR 5.9), two missing 6.55 (CoR 9.5), all
missing 19.45 (CoR 12.1), one-camera 0.59 (CoR 1.3).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from dataclasses import dataclass

import _common
import numpy as np
from scipy.interpolate import CubicSpline

from mocapflow.io.bvh import read_bvh
from mocapflow.io.markers import read_markers
from mocapflow.mocap.calibration import build_skeleton
from mocapflow.mocap.filling import FillerConfig, GapFiller
from mocapflow.mocap.model import SkeletonModel
from mocapflow.mocap.rigidfit import kabsch
from mocapflow.mocap.rigs import make_rig
from mocapflow.mocap.simulator import SimulatorConfig, camera_ring, simulate, truth_skeleton

GAP_S = 3.0
HISTORY_S = 6.0  # frames filled before a gap with a skeleton: more than the filler's 5 s twist and kinematic windows
RING = camera_ring(8, 4000.0, 2500.0)  # the simulator's camera placement, about the recording's centre
CASES = ("one missing", "two missing", "all missing", "one on each of two segments", "one-camera, one on each")
METHODS = ("skeleton", "thesis", "learned", "kalman", "linear", "spline")
THESIS = {"one missing": "2.58/5.9", "two missing": "6.55/9.5", "all missing": "19.45/12.1",
          "one on each of two segments": "-/6.35", "one-camera, one on each": "0.59/1.3"}


@dataclass
class Dataset:
    name: str
    observed: np.ndarray  # (F, N, 3) what the filler sees before deletion
    truth: np.ndarray  # (F, N, 3) what filled markers are compared with
    labels: list[str]
    rate: float
    skeleton: SkeletonModel
    centres: dict[str, np.ndarray]  # joint name -> (F, 3) reference joint centres
    learn_from_s: float | None  # earliest gap start for the learned filler, None: not run


def segment_poses(skeleton: SkeletonModel, labels: list[str], positions: np.ndarray) -> dict[str, tuple]:
    """Each segment's pose in every frame fitted to ``positions`` (all its markers needed)."""
    out = {}
    for seg in skeleton.segments:
        idx = [labels.index(m) for m in seg.markers]
        x = positions[:, idx]
        ok = np.isfinite(x).all((1, 2))
        local = np.broadcast_to(np.array(seg.marker_offsets), x.shape)
        r, t, fit = kabsch(local, np.where(ok[:, None, None], x, 0.0), np.ones(x.shape[:2]))
        out[seg.name] = (np.where((ok & fit)[:, None, None], r, np.nan), np.where((ok & fit)[:, None], t, np.nan))
    return out


def joint_centres(skeleton: SkeletonModel, labels: list[str], positions: np.ndarray) -> dict[str, np.ndarray]:
    """Joint centres per frame from both segments' poses, averaged (Aristidou eq. 4.29)."""
    poses = segment_poses(skeleton, labels, positions)
    out = {}
    for j in skeleton.joints:
        (rp, tp), (rc, tc) = poses[j.parent], poses[j.child]
        out[j.name] = 0.5 * (rp @ np.array(j.parent_offset) + tp + rc @ np.array(j.child_offset) + tc)
    return out


def simulated(frames: int) -> Dataset:
    bvh_path = _common.DATA / "cmu_131_01.bvh"
    bvh = read_bvh(bvh_path) if bvh_path.is_file() else None
    config = SimulatorConfig(rig="human", rate=120, noise_mm=0.5, skin_mm=2.0, seed=1,
                             bvh=str(bvh_path) if bvh is not None else None)
    rec = simulate(config, frames, bvh)
    skeleton = truth_skeleton(make_rig("human"), rec.true_positions[0])
    centres = dict(zip(rec.joint_names, rec.joint_centres.transpose(1, 0, 2), strict=True))
    motion = "CMU 131_01 BVH motion" if bvh is not None else "synthetic motion"
    return Dataset(f"simulated human ({motion}, 0.5 mm noise, 2 mm skin artefact)", rec.positions,
                   rec.true_positions, rec.labels, rec.rate, skeleton, centres, 8.0)


def real(file: str, groups: dict[str, list[str]], learn_from_s: float | None) -> Dataset | None:
    path = _common.DATA / file
    if not path.is_file():
        return None
    data = read_markers(path)
    index = {label: i for i, label in enumerate(data.labels)}
    skeleton = build_skeleton(data.positions, data.labels, data.rate,
                              [[index[m] for m in g] for g in groups.values()], "closed-form")
    names = dict(zip([s.name for s in skeleton.segments], groups, strict=True))
    skeleton = skeleton.model_copy(update={
        "segments": [s.model_copy(update={"name": names[s.name]}) for s in skeleton.segments],
        "joints": [j.model_copy(update={"name": f"{names[j.parent]}-{names[j.child]}", "parent": names[j.parent],
                                        "child": names[j.child]}) for j in skeleton.joints],
        "root": names[skeleton.root]})
    centres = joint_centres(skeleton, data.labels, data.positions)
    return Dataset(f"{file} ({data.n_frames} frames at {data.rate:g} Hz)", data.positions, data.positions,
                   data.labels, data.rate, skeleton, centres, learn_from_s)


LOWER_BODY = {  # three markers of each cluster, as in the thesis; the fourth stays outside the skeleton
    "pelvis": ["LASI", "RASI", "LPSI", "RPSI"], "lthigh": ["LTH1", "LTH2", "LTH3"], "lshank": ["LSH1", "LSH2", "LSH3"],
    "lfoot": ["LTOE", "LMT5", "LCAL", "LCUN"], "rthigh": ["RTH1", "RTH2", "RTH3"], "rshank": ["RSH1", "RSH2", "RSH3"],
    "rfoot": ["RTOE", "RMT5", "RCAL", "RCUN"]}
CMU = {
    "pelvis": ["LFWT", "RFWT", "LBWT", "RBWT"], "torso": ["CLAV", "STRN", "C7", "T10", "RBAC"],
    "head": ["LFHD", "RFHD", "LBHD", "RBHD"], "lupperarm": ["LSHO", "LUPA", "LELB"],
    "lforearm": ["LFRM", "LWRA", "LWRB"], "rupperarm": ["RSHO", "RUPA", "RELB"], "rforearm": ["RFRM", "RWRA", "RWRB"],
    "lleg": ["LTHI", "LKNE", "LSHN"], "lfoot": ["LANK", "LHEE", "LMT5", "LTOE"], "rleg": ["RTHI", "RKNE", "RSHN"],
    "rfoot": ["RANK", "RHEE", "RMT5", "RTOE"]}


def pick(ds: Dataset, case: str, rng: np.random.Generator) -> tuple[list[str], list[str]]:
    """Markers to hide and the joints to score for one run of ``case``: segments with 3+ markers and joints."""
    segs = {s.name: s.markers for s in ds.skeleton.segments}
    joints = ds.skeleton.joints
    if case in ("one on each of two segments", "one-camera, one on each"):
        j = joints[rng.integers(len(joints))]
        return [str(rng.choice(segs[j.parent])), str(rng.choice(segs[j.child]))], [j.name]
    candidates = [s for s, m in segs.items() if len(m) >= 3 and any(s in (j.parent, j.child) for j in joints)]
    seg = str(rng.choice(candidates))
    count = {"one missing": 1, "two missing": 2, "all missing": len(segs[seg])}[case]
    return [str(m) for m in rng.choice(segs[seg], count, replace=False)], [
        j.name for j in joints if seg in (j.parent, j.child)]


def single_cameras(ds: Dataset, count: int, rng: np.random.Generator) -> np.ndarray:
    """(count, 3) centres of the cameras that see each of ``count`` hidden markers through a gap: each drawn from an
    8-camera ring (radius 4 m, height 2.5 m) about the recording's horizontal centre."""
    centre = np.nanmean(ds.truth, axis=(0, 1)) * [1.0, 1.0, 0.0]
    return centre + RING[rng.integers(0, len(RING), count)]


def run_filler(ds: Dataset, x: np.ndarray, start: int, stop: int, hidden: list[int], cameras: np.ndarray | None,
               config: FillerConfig, skeleton: SkeletonModel | None) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Fill frames first..stop-1 (first: ``HISTORY_S`` before the gap with a skeleton, else 0); filled frames and
    joints.
    With ``cameras`` (one per hidden marker), each hidden marker arrives as the ray from its camera through it."""
    first = max(start - round(HISTORY_S * ds.rate), 0) if skeleton is not None else 0
    filler = GapFiller(ds.labels, ds.rate, config, skeleton)
    out = np.full((stop - start, len(ds.labels), 3), np.nan)
    centres: dict[str, np.ndarray] = {}
    for f in range(first, stop):
        ray = None
        if cameras is not None and f >= start:
            ray = np.full((len(ds.labels), 6), np.nan)
            ray[hidden, :3] = cameras
            ray[hidden, 3:] = ds.truth[f, hidden] - cameras
        result = filler.update(x[f], ray)
        if f >= start:
            out[f - start] = result.positions
            if result.joint_centres is not None:
                for name, c in zip(filler.joint_names, result.joint_centres, strict=True):
                    centres.setdefault(name, np.full((stop - start, 3), np.nan))[f - start] = c
    return out, centres


def interpolate(x: np.ndarray, start: int, stop: int, hidden: list[int], kind: str, rate: float) -> np.ndarray:
    """Linear or cubic-spline interpolation across the gap from the frames around it (1 s each side)."""
    out = x[start:stop].copy()
    frames = np.arange(len(x))
    window = (frames >= start - round(rate)) & (frames < stop + round(rate))
    for m in hidden:
        known = window & np.isfinite(x[:, m]).all(1)
        if kind == "linear":
            for axis in range(3):
                out[:, m, axis] = np.interp(frames[start:stop], frames[known], x[known, m, axis])
        else:
            out[:, m] = CubicSpline(frames[known], x[known, m])(frames[start:stop])
    return out


def one_run(ds: Dataset, case: str, rng: np.random.Generator) -> dict[str, tuple[float, float]]:
    gap = round(GAP_S * ds.rate)
    names, joints = pick(ds, case, rng)
    hidden = [ds.labels.index(m) for m in names]
    earliest = round(ds.rate)
    start = int(rng.integers(earliest, len(ds.observed) - gap - round(ds.rate)))
    stop = start + gap
    x = ds.observed.copy()
    x[start:stop, hidden] = np.nan
    rays = single_cameras(ds, len(hidden), rng) if case.startswith("one-camera") else None
    late = ds.learn_from_s is not None and start >= ds.learn_from_s * ds.rate
    fills: dict[str, Callable[[], tuple[np.ndarray, dict[str, np.ndarray] | None]]] = {
        "skeleton": lambda: run_filler(ds, x, start, stop, hidden, rays, FillerConfig(), ds.skeleton),
        "thesis": lambda: run_filler(ds, x, start, stop, hidden, rays, FillerConfig(
            joint_anchors="hidden", hidden_rotation="rotor", ray_distances=False), ds.skeleton),
        "learned": lambda: (run_filler(ds, x, start, stop, hidden, rays, FillerConfig(), None)[0], {}),
        "kalman": lambda: (run_filler(ds, x, start, stop, hidden, rays, FillerConfig(
            learn=False, extrapolate_max_s=None), None)[0], None),
        "linear": lambda: (interpolate(x, start, stop, hidden, "linear", ds.rate), None),
        "spline": lambda: (interpolate(x, start, stop, hidden, "spline", ds.rate), None),
    }
    scores = {}
    for method, fill in fills.items():
        if method == "learned" and not late:
            continue
        if method in ("linear", "spline") and rays is not None:
            continue  # interpolation has no use for a ray
        out, centres = fill()
        marker = float(np.nanmean(np.linalg.norm(out[:, hidden] - ds.truth[start:stop, hidden], axis=-1)))
        if centres is None:  # the same skeleton fitted to the filled markers
            frames = ds.observed[start:stop].copy()
            frames[:, hidden] = out[:, hidden]
            centres = joint_centres(ds.skeleton, ds.labels, frames)
        cor = [np.linalg.norm(centres[j] - ds.centres[j][start:stop], axis=-1) for j in joints if j in centres]
        scores[method] = (marker, float(np.nanmean(cor)) if cor else np.nan)
    return scores


def table(ds: Dataset, runs: int, seed: int, cases: tuple[str, ...]) -> None:
    print(f"\n{ds.name}: {len(ds.labels)} markers, {len(ds.skeleton.segments)} segments, "
          f"{len(ds.skeleton.joints)} joints; {runs} gaps of {GAP_S:g} s per case; marker mm / joint centre mm")
    print(f"{'case':<30}" + "".join(f"{m:>15}" for m in METHODS) + f"{'thesis':>12}")
    for case in cases:
        rng = np.random.default_rng([seed, CASES.index(case)])
        results: dict[str, list[tuple[float, float]]] = {}
        for _ in range(runs):
            for method, score in one_run(ds, case, rng).items():
                results.setdefault(method, []).append(score)
        cells = []
        for method in METHODS:
            if method not in results:
                cells.append(f"{'-':>15}")
                continue
            marker, cor = np.array(results[method]).T
            marker, cor = marker.mean(), cor[np.isfinite(cor)].mean() if np.isfinite(cor).any() else np.nan
            cells.append(f"{marker:>8.2f}/{cor:<6.1f}" if np.isfinite(cor) else f"{marker:>8.2f}/{'-':<6}")
        print(f"{case:<30}" + "".join(cells) + f"{THESIS[case]:>12}", flush=True)


def camera_table(frames: int) -> None:
    """The simulator's camera model on a simulated human: markers seen by one camera arrive as rays, markers seen by
    none are missing, as the body occludes them. Error (mm) of the filled markers against the truth, per kind."""
    bvh_path = _common.DATA / "cmu_131_01.bvh"
    bvh = read_bvh(bvh_path) if bvh_path.is_file() else None
    print(f"\nsimulated human, camera model ({'CMU 131_01 BVH' if bvh else 'synthetic'} motion, 0.5 mm noise, 2 mm "
          f"skin artefact), {frames} frames at 120 Hz; mean error (mm) of single-camera / unseen markers")
    print(f"{'cameras':<8}{'points %':>10}{'rays %':>8}{'unseen %':>10}{'rays used':>16}{'projection only':>18}"
          f"{'rays ignored':>16}")
    for cameras in (3, 4):
        config = SimulatorConfig(rig="human", rate=120, noise_mm=0.5, skin_mm=2.0, seed=1, cameras=cameras,
                                 bvh=str(bvh_path) if bvh is not None else None)
        rec = simulate(config, frames, bvh)
        assert rec.rays is not None
        skeleton = truth_skeleton(make_rig("human"), rec.true_positions[0])
        ray = np.isfinite(rec.rays).all(-1)
        unseen = ~rec.visible & ~ray
        cells = []
        for config_, rays in ((FillerConfig(), rec.rays), (FillerConfig(ray_distances=False), rec.rays),
                              (FillerConfig(), None)):
            filler = GapFiller(rec.labels, rec.rate, config_, skeleton)
            out = np.array([filler.update(rec.positions[f], None if rays is None else rays[f]).positions
                            for f in range(frames)])
            error = np.linalg.norm(out - rec.true_positions, axis=-1)
            cells.append(f"{np.nanmean(error[ray]):.2f} / {np.nanmean(error[unseen]):.2f}")
        print(f"{cameras:<8}{100 * rec.visible.mean():>10.1f}{100 * ray.mean():>8.1f}{100 * unseen.mean():>10.2f}"
              f"{cells[0]:>16}{cells[1]:>18}{cells[2]:>16}", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=10, help="gaps per case and dataset (default 10, as in the thesis)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--case", choices=CASES, action="append", help="only this case (repeatable; default all)")
    parser.add_argument("--data", choices=("simulated", "lowerbody", "cmu"), action="append",
                        help="only this dataset (repeatable; default all)")
    args = parser.parse_args()
    cases = tuple(args.case or CASES)
    wanted = set(args.data or ("simulated", "lowerbody", "cmu"))
    if "simulated" in wanted and "one-camera, one on each" in cases:
        camera_table(3000)
    loaders = {"simulated": lambda: simulated(3000),
               "lowerbody": lambda: real("lowerbody_clusters_knee_0401.c3d", LOWER_BODY, 8.0),
               "cmu": lambda: real("cmu_85_02.c3d", CMU, None)}
    for name, load in loaders.items():
        if name not in wanted:
            continue
        ds = load()
        if ds is None:
            print(f"\n(real data folder {_common.DATA} absent: {name} skipped)")
            continue
        table(ds, args.runs, args.seed, cases)


if __name__ == "__main__":
    main()
