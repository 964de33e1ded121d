"""C3D reading and writing: real exporters' files, round trips checked by ezc3d and by the independent ``c3d`` package,
and every malformed file ending in a MocapFileError that names it."""

from __future__ import annotations

import subprocess
import sys
import warnings
from collections.abc import Callable
from pathlib import Path

import c3d as c3d_package
import ezc3d
import numpy as np
import pytest

import mocapflow.io.c3d as c3d_module
from mocapflow.errors import MocapFileError
from mocapflow.io.c3d import read_c3d, write_c3d
from mocapflow.io.markerdata import FLAG_ESTIMATED, FLAG_MISSING, FLAG_OBSERVED, MarkerData, clean_labels
from mocapflow.io.markers import read_markers, write_markers


def synthetic(frames: int = 60, markers: int = 6, first_frame: int = 1, seed: int = 0) -> MarkerData:
    """Random trajectories with a gap, estimated samples of several codes and one extra point with a gap."""
    rng = np.random.default_rng(seed)
    positions = rng.uniform(-2000.0, 2000.0, (frames, markers, 3))
    flags = np.full((frames, markers), FLAG_OBSERVED, np.uint8)
    positions[5:9, 1] = np.nan
    flags[5:9, 1] = FLAG_MISSING
    flags[10:20, 2] = FLAG_ESTIMATED
    flags[20:25, 2] = 7
    flags[30:33, markers - 1] = 15
    flags[0:3, 0] = 3
    joint = rng.uniform(-500.0, 500.0, (frames, 3))
    joint[40] = np.nan
    return MarkerData(positions, [f"M{i}" for i in range(markers)], 120.0, first_frame, flags, {"LKNE_JC": joint})


def as_float32(values: np.ndarray) -> np.ndarray:
    return values.astype(np.float32).astype(np.float64)


def assert_same_markers(read: MarkerData, truth: MarkerData) -> None:
    """Equal after the float32 of the file: same labels, rate, numbering, NaNs, values, flags and extra points."""
    assert read.labels == truth.labels
    assert read.rate == pytest.approx(truth.rate)
    assert read.first_frame == truth.first_frame
    np.testing.assert_array_equal(read.positions, as_float32(truth.positions))
    np.testing.assert_array_equal(read.flags, truth.sample_flags())
    assert list(read.extra) == list(truth.extra)
    for name, point in truth.extra.items():
        np.testing.assert_array_equal(read.extra[name], as_float32(point))


def read_with_c3d_package(path: Path) -> tuple[np.ndarray, np.ndarray, list[str], int, float]:
    """Points (F, N, 5: x, y, z, residual, camera byte), labels, first frame and rate as the ``c3d`` package reads
    them."""
    with path.open("rb") as handle, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "no analog data found"
        reader = c3d_package.Reader(handle)
        points = np.stack([frame for _, frame, _ in reader.read_frames()])
        labels = [str(label).strip() for label in reader.get("POINT:LABELS").string_array]
        more = reader.get("POINT:LABELS2")
        labels += [str(label).strip() for label in more.string_array] if more is not None else []
        # The package weighs the high word of ACTUAL_START_FIELD by 65535 (and so reads one frame too many past
        # 65535): decode both 16-bit word pairs as the C3D manual specifies.
        start, end = reader.get("TRIAL:ACTUAL_START_FIELD"), reader.get("TRIAL:ACTUAL_END_FIELD")
        if start is None:
            return points, labels, reader.header.first_frame, reader.point_rate
        first_frame, last_frame = (int(p.uint16_array[0]) + int(p.uint16_array[1]) * 65536 for p in (start, end))
        return points[: last_frame - first_frame + 1], labels, first_frame, reader.point_rate


def write_foreign(path: Path, positions: np.ndarray, labels: list[str], *, units: str = "mm",
                  residuals: np.ndarray | None = None, rate: float = 100.0) -> ezc3d.c3d:
    """A C3D file as another program writes it (no MOCAPFLOW group); returns the ezc3d object before writing."""
    frames, markers, _ = positions.shape
    c3d = ezc3d.c3d()
    c3d["parameters"]["POINT"]["RATE"]["value"] = np.array([rate])
    c3d["parameters"]["POINT"]["UNITS"]["value"] = [units]
    c3d["parameters"]["POINT"]["LABELS"]["value"] = list(labels)
    points = np.ones((4, markers, frames))
    points[:3] = positions.transpose(2, 1, 0)
    c3d["data"]["points"] = points
    if residuals is not None:
        c3d["data"]["meta_points"] = {
            "residuals": residuals.T[None].astype(np.float64),
            "camera_masks": np.zeros((7, markers, frames), dtype=bool),
        }
    c3d.write(str(path))
    return c3d


# Real files ------------------------------------------------------------------------------------------------------


def test_cmu_file_matches_the_c3d_package(real_file: Callable[[str], Path]) -> None:
    path = real_file("cmu_85_02.c3d")
    data = read_c3d(path)
    points, labels, first_frame, rate = read_with_c3d_package(path)
    assert data.positions.shape == (810, 41, 3)
    assert data.rate == 120.0 and rate == 120.0
    assert data.first_frame == first_frame == 1
    assert labels[0] == "Male:LFWT" and data.labels[0] == "LFWT"
    assert data.labels == [label.removeprefix("Male:") for label in labels]
    assert not np.isnan(data.positions).any()
    np.testing.assert_array_equal(data.positions, points[..., :3])
    assert (data.flags == FLAG_OBSERVED).all()  # every residual is 0 in this export: no residuals recorded
    assert read_c3d(path, strip_prefix=False).labels == labels


def test_vicon_file_gaps_are_nan(real_file: Callable[[str], Path]) -> None:
    path = real_file("lowerbody_clusters_knee_0401.c3d")
    data = read_c3d(path)
    points, labels, first_frame, _ = read_with_c3d_package(path)
    assert data.positions.shape == (3379, 40, 3)
    assert data.rate == 100.0
    assert data.first_frame == first_frame == 941
    assert data.labels == labels
    gaps = np.isnan(data.positions[..., 0])
    np.testing.assert_array_equal(gaps, points[..., 3] < 0)
    assert 0.005 < gaps.mean() < 0.009
    assert data.labels[int(gaps.sum(axis=0).argmax())] == "RMAK"
    np.testing.assert_array_equal(data.positions[~gaps], points[..., :3][~gaps])
    np.testing.assert_array_equal(data.flags, np.where(gaps, FLAG_MISSING, FLAG_OBSERVED))


@pytest.mark.parametrize("name", ["cmu_85_02.c3d", "lowerbody_clusters_knee_0401.c3d"])
def test_real_file_round_trip(name: str, tmp_path: Path, real_file: Callable[[str], Path]) -> None:
    original = read_c3d(real_file(name))
    out = tmp_path / "copy.c3d"
    write_c3d(out, original)
    assert_same_markers(read_c3d(out), original)
    points, labels, first_frame, rate = read_with_c3d_package(out)
    assert labels == original.labels and first_frame == original.first_frame and rate == original.rate
    gaps = np.isnan(original.positions[..., 0])
    np.testing.assert_array_equal(points[..., 3] < 0, gaps)
    np.testing.assert_array_equal(points[..., :3][~gaps], original.positions[~gaps])


# Synthetic round trips ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("first_frame", [0, 1, 941, 70000])
def test_synthetic_round_trip_keeps_values_gaps_flags_and_extra_points(first_frame: int, tmp_path: Path) -> None:
    data = synthetic(first_frame=first_frame)
    out = tmp_path / "synthetic.c3d"
    write_markers(out, data)
    assert_same_markers(read_markers(out), data)

    # The independent reader sees the same numbers, frame numbering and the C3D residual convention.
    points, labels, package_first, _ = read_with_c3d_package(out)
    assert labels == [*data.labels, "LKNE_JC"]
    assert package_first == first_frame and len(points) == data.n_frames
    flags = data.sample_flags()
    residual = points[:, : data.n_markers, 3]
    np.testing.assert_array_equal(residual < 0, flags == FLAG_MISSING)
    np.testing.assert_array_equal(residual == 0, flags >= FLAG_ESTIMATED)
    np.testing.assert_array_equal(residual > 0, flags == FLAG_OBSERVED)
    present = flags != FLAG_MISSING
    np.testing.assert_array_equal(points[:, : data.n_markers, :3][present], as_float32(data.positions[present]))
    joint = data.extra["LKNE_JC"]
    np.testing.assert_array_equal(points[:, -1, 3] < 0, np.isnan(joint[:, 0]))
    np.testing.assert_array_equal(points[~np.isnan(joint[:, 0]), -1, :3], as_float32(joint[~np.isnan(joint[:, 0])]))

    # ezc3d itself agrees on the residuals.
    raw = ezc3d.c3d(str(out))
    np.testing.assert_array_equal(raw["data"]["meta_points"]["residuals"][0, : data.n_markers].T, residual)


def test_more_than_255_labels_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    data = MarkerData(rng.normal(0.0, 800.0, (8, 300, 3)), [f"P{i:03d}" for i in range(300)], 60.0, 1)
    out = tmp_path / "many.c3d"
    write_c3d(out, data)
    point = ezc3d.c3d(str(out))["parameters"]["POINT"]
    assert len(point["LABELS"]["value"]) == 255 and len(point["LABELS2"]["value"]) == 45
    assert_same_markers(read_c3d(out), data)
    points, labels, _, _ = read_with_c3d_package(out)
    assert labels == data.labels
    np.testing.assert_array_equal(points[..., :3], as_float32(data.positions))


def test_long_estimation_runs_split_across_parameters(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setattr(c3d_module, "MAX_RUN", 4)
    monkeypatch.setattr(c3d_module, "RUNS_PER_PARAMETER", 3)
    data = synthetic()
    out = tmp_path / "runs.c3d"
    write_c3d(out, data)
    group = ezc3d.c3d(str(out))["parameters"]["MOCAPFLOW"]
    assert {"FLAG_RUNS", "FLAG_RUNS2", "FLAG_RUNS3"} <= set(group)
    np.testing.assert_array_equal(read_c3d(out).flags, data.sample_flags())


def test_too_many_estimation_runs_degrade_to_estimated(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setattr(c3d_module, "RUNS_PER_PARAMETER", 2)
    monkeypatch.setattr(c3d_module, "MAX_RUN_PARAMETERS", 1)
    data = synthetic()
    with pytest.warns(UserWarning, match="runs of estimation codes"):
        write_c3d(tmp_path / "many_runs.c3d", data)
    flags = data.sample_flags()
    np.testing.assert_array_equal(read_c3d(tmp_path / "many_runs.c3d").flags, np.minimum(flags, FLAG_ESTIMATED))


def test_flags_default_to_the_positions(tmp_path: Path) -> None:
    data = synthetic()
    data.flags = None
    out = tmp_path / "noflags.c3d"
    write_c3d(out, data)
    flags = read_c3d(out).flags
    np.testing.assert_array_equal(flags, np.where(np.isnan(data.positions[..., 0]), FLAG_MISSING, FLAG_OBSERVED))


# Other programs' files ------------------------------------------------------------------------------------------


@pytest.mark.parametrize(("units", "factor"), [("m", 1000.0), ("cm", 10.0), ("mm", 1.0)])
def test_units_are_converted_to_mm(units: str, factor: float, tmp_path: Path) -> None:
    positions = np.random.default_rng(2).uniform(-2.0, 2.0, (5, 3, 3))
    write_foreign(tmp_path / "units.c3d", positions, ["A", "B", "C"], units=units)
    data = read_c3d(tmp_path / "units.c3d")
    np.testing.assert_allclose(data.positions, as_float32(positions) * factor, rtol=1e-12)


def test_unknown_unit_is_an_error(tmp_path: Path) -> None:
    write_foreign(tmp_path / "feet.c3d", np.ones((3, 1, 3)), ["A"], units="ft")
    with pytest.raises(MocapFileError, match=r"feet\.c3d.*'ft'"):
        read_c3d(tmp_path / "feet.c3d")


def test_all_zero_samples_are_missing(tmp_path: Path) -> None:
    positions = np.random.default_rng(3).uniform(1.0, 100.0, (6, 2, 3))
    positions[2, 1] = 0.0
    positions[3, 0] = [0.0, 0.0, 5.0]  # one zero coordinate is a real position
    write_foreign(tmp_path / "zeros.c3d", positions, ["A", "B"])
    data = read_c3d(tmp_path / "zeros.c3d")
    assert np.isnan(data.positions[2, 1]).all() and data.flags[2, 1] == FLAG_MISSING
    assert np.isnan(data.positions).sum() == 3
    assert data.positions[3, 0, 2] == 5.0 and data.flags[3, 0] == FLAG_OBSERVED


def test_residual_zero_means_estimated_only_where_residuals_are_recorded(tmp_path: Path) -> None:
    positions = np.random.default_rng(4).uniform(1.0, 100.0, (6, 2, 3))
    residuals = np.full((6, 2), 3.0)
    residuals[1:3, 0] = 0.0
    residuals[4, 1] = -1.0
    write_foreign(tmp_path / "residuals.c3d", positions, ["A", "B"], residuals=residuals)
    expected = np.where(residuals > 0, FLAG_OBSERVED, np.where(residuals == 0, FLAG_ESTIMATED, FLAG_MISSING))
    np.testing.assert_array_equal(read_c3d(tmp_path / "residuals.c3d").flags, expected)
    write_foreign(tmp_path / "no_residuals.c3d", positions, ["A", "B"], residuals=np.zeros((6, 2)))
    assert (read_c3d(tmp_path / "no_residuals.c3d").flags == FLAG_OBSERVED).all()


def test_analog_channels_and_model_outputs_are_skipped(tmp_path: Path) -> None:
    positions = np.random.default_rng(5).uniform(1.0, 100.0, (5, 3, 3))
    c3d = ezc3d.c3d()
    c3d["parameters"]["POINT"]["RATE"]["value"] = np.array([100.0])
    c3d["parameters"]["POINT"]["LABELS"]["value"] = ["A", "LKneeAngles", "B"]
    c3d["parameters"]["POINT"]["ANGLES"] = {"type": -1, "description": "", "is_locked": False, "value": ["LKneeAngles"]}
    points = np.ones((4, 3, 5))
    points[:3] = positions.transpose(2, 1, 0)
    c3d["data"]["points"] = points
    c3d["parameters"]["ANALOG"]["RATE"]["value"] = np.array([1000.0])
    c3d["parameters"]["ANALOG"]["LABELS"]["value"] = ["EMG1", "EMG2"]
    c3d["data"]["analogs"] = np.random.default_rng(6).normal(size=(1, 2, 50))
    c3d.write(str(tmp_path / "analog.c3d"))
    data = read_c3d(tmp_path / "analog.c3d")
    assert data.labels == ["A", "B"]
    np.testing.assert_array_equal(data.positions, as_float32(positions[:, [0, 2]]))


def test_prefixes_kept_where_stripping_would_clash(tmp_path: Path) -> None:
    labels = ["Anna:HEAD", "Ben:HEAD", "Anna:LKNE", "RKNE", "", "RKNE"]
    assert clean_labels(labels, True) == ["Anna:HEAD", "Ben:HEAD", "LKNE", "RKNE", "point5", "RKNE_2"]
    assert clean_labels(labels, False) == ["Anna:HEAD", "Ben:HEAD", "Anna:LKNE", "RKNE", "point5", "RKNE_2"]
    assert clean_labels(["Anna:LKNE_JC", "LKNE_JC_2"], True, taken=["LKNE_JC"]) == ["Anna:LKNE_JC", "LKNE_JC_2"]
    write_foreign(tmp_path / "two.c3d", np.ones((2, 4, 3)), labels[:4])
    assert read_c3d(tmp_path / "two.c3d").labels == ["Anna:HEAD", "Ben:HEAD", "LKNE", "RKNE"]


# Bad files ------------------------------------------------------------------------------------------------------


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(MocapFileError, match=r"absent\.c3d"):
        read_c3d(tmp_path / "absent.c3d")
    with pytest.raises(MocapFileError, match=r"absent\.c3d"):
        read_markers(tmp_path / "absent.c3d")


def test_text_file_named_c3d(tmp_path: Path) -> None:
    path = tmp_path / "notes.c3d"
    path.write_text("These are not markers.\n" * 40)
    for reader in (read_c3d, read_markers):
        with pytest.raises(MocapFileError, match=r"notes\.c3d: not a C3D file"):
            reader(path)


def test_truncated_file(tmp_path: Path, real_file: Callable[[str], Path]) -> None:
    source = real_file("cmu_85_02.c3d").read_bytes()
    path = tmp_path / "half.c3d"
    path.write_bytes(source[: len(source) // 2])
    with pytest.raises(MocapFileError, match=r"half\.c3d: truncated"):
        read_c3d(path)


def test_file_without_points(tmp_path: Path) -> None:
    c3d = ezc3d.c3d()
    c3d["parameters"]["POINT"]["RATE"]["value"] = np.array([100.0])
    c3d["data"]["points"] = np.zeros((4, 0, 10))
    c3d.write(str(tmp_path / "empty.c3d"))
    with pytest.raises(MocapFileError, match=r"empty\.c3d: .*no 3D points"):
        read_c3d(tmp_path / "empty.c3d")


def test_parameter_promising_more_data_than_its_record(tmp_path: Path) -> None:
    """ezc3d would read such a file for minutes: it must be refused before."""
    out = tmp_path / "ok.c3d"
    write_c3d(out, synthetic())
    raw = bytearray(out.read_bytes())
    name = raw.index(b"EXTRA_USED")
    raw[name + len("EXTRA_USED") + 3] = 15  # number of dimensions, after the offset word and the type
    bad = tmp_path / "dims.c3d"
    bad.write_bytes(bytes(raw))
    with pytest.raises(MocapFileError, match=r"dims\.c3d: corrupt C3D parameter section"):
        read_c3d(bad)


FUZZ = """
import sys
import numpy as np
from mocapflow.errors import MocapFileError
from mocapflow.io.c3d import read_c3d
source = open(sys.argv[1], "rb").read()
rng = np.random.default_rng(7)
outcomes = []
for case in range(int(sys.argv[3])):
    raw = bytearray(source)
    span = [512, 4096, len(source)][case % 3]
    for position in rng.integers(0, span, size=rng.integers(1, 12)):
        raw[position] = rng.integers(0, 256)
    if case % 4 == 3:
        raw = raw[: rng.integers(0, len(raw))]
    open(sys.argv[2], "wb").write(raw)
    try:
        read_c3d(sys.argv[2])
        outcomes.append("read")
    except MocapFileError:
        outcomes.append("refused")
print(" ".join(outcomes))
"""


@pytest.mark.integration
def test_corrupted_files_are_read_or_refused_never_crash(tmp_path: Path, real_file: Callable[[str], Path]) -> None:
    """Random byte damage: every file is read or refused with MocapFileError; the process neither crashes nor hangs."""
    source = real_file("cmu_85_02.c3d")
    result = subprocess.run([sys.executable, "-c", FUZZ, str(source), str(tmp_path / "damaged.c3d"), "40"],
                            check=False, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-2000:]
    outcomes = result.stdout.split()
    assert len(outcomes) == 40 and "refused" in outcomes


# The data class and format dispatch -----------------------------------------------------------------------------


def test_marker_data_rejects_inconsistent_shapes() -> None:
    with pytest.raises(ValueError, match="labels"):
        MarkerData(np.zeros((2, 3, 3)), ["A", "B"], 100.0)
    with pytest.raises(ValueError, match="duplicate"):
        MarkerData(np.zeros((2, 2, 3)), ["A", "A"], 100.0)
    with pytest.raises(ValueError, match="flags"):
        MarkerData(np.zeros((2, 2, 3)), ["A", "B"], 100.0, flags=np.zeros((2, 3)))
    with pytest.raises(ValueError, match="extra"):
        MarkerData(np.zeros((2, 2, 3)), ["A", "B"], 100.0, extra={"A": np.zeros((2, 3))})


def test_dispatch_by_content_then_extension(tmp_path: Path) -> None:
    data = synthetic()
    write_markers(tmp_path / "take.c3d", data)
    renamed = tmp_path / "take.dat"
    renamed.write_bytes((tmp_path / "take.c3d").read_bytes())
    assert_same_markers(read_markers(renamed), data)
    upper = tmp_path / "TAKE.C3D"
    write_markers(upper, data)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["TAKE.C3D", "take.c3d", "take.dat"]
    with pytest.raises(MocapFileError, match=r"take\.bvh"):
        write_markers(tmp_path / "take.bvh", data)
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(MocapFileError, match=r"notes\.txt: neither a C3D nor a TRC"):
        read_markers(tmp_path / "notes.txt")
