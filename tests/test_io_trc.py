"""TRC reading and writing: round trips, real C3D files through TRC and back, and hand-written files in the layouts
other programs produce."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from mocapflow.errors import MocapFileError
from mocapflow.io.c3d import read_c3d, write_c3d
from mocapflow.io.markers import FLAG_ESTIMATED, FLAG_MISSING, FLAG_OBSERVED, MarkerData, read_markers, write_markers
from mocapflow.io.trc import HEADER_KEYS, read_trc, write_trc


def as_float32(values: np.ndarray) -> np.ndarray:
    return values.astype(np.float32).astype(np.float64)


def synthetic(frames: int = 40, markers: int = 5, first_frame: int = 1) -> MarkerData:
    rng = np.random.default_rng(0)
    positions = rng.uniform(-2000.0, 2000.0, (frames, markers, 3))
    positions[3:7, 1] = np.nan
    positions[-1, markers - 1] = np.nan
    positions[10, 0] = [1e-7, -0.5, 123456.789]  # tiny, fractional and large values survive the text form
    flags = np.where(np.isnan(positions[..., 0]), FLAG_MISSING, FLAG_OBSERVED).astype(np.uint8)
    labels = [f"Sub:M{i}" if i == 2 else f"M{i}" for i in range(markers)]
    return MarkerData(positions, labels, 120.0, first_frame, flags)


def test_round_trip_and_header(tmp_path: Path) -> None:
    data = synthetic(first_frame=941)
    out = tmp_path / "walk.trc"
    write_trc(out, data)
    lines = out.read_text().split("\n")
    assert lines[0].split("\t") == ["PathFileType", "4", "(X/Y/Z)", "walk.trc"]
    assert lines[1].split("\t") == list(HEADER_KEYS)
    assert lines[2].split("\t") == ["120", "120", "40", "5", "mm", "120", "941", "40"]
    assert lines[3].split("\t")[:6] == ["Frame#", "Time", "M0", "", "", "M1"]
    assert lines[4].split("\t")[:5] == ["", "", "X1", "Y1", "Z1"]
    assert lines[5] == ""
    row = lines[6 + 3].split("\t")  # frame 944: marker M1 is missing
    assert row[:2] == ["944", "0.025"] and row[5:8] == ["", "", ""]

    read = read_trc(out)
    assert read.labels == ["M0", "M1", "M2", "M3", "M4"]
    assert read_trc(out, strip_prefix=False).labels[2] == "Sub:M2"
    assert read.rate == 120.0 and read.first_frame == 941
    np.testing.assert_array_equal(np.isnan(read.positions), np.isnan(data.positions))
    np.testing.assert_allclose(read.positions, data.positions, rtol=1e-8, atol=0)
    np.testing.assert_array_equal(read.flags, data.flags)


def test_estimated_samples_read_back_observed_and_extra_points_as_markers(tmp_path: Path) -> None:
    data = synthetic()
    data.flags[20:25, 3] = FLAG_ESTIMATED
    data.extra = {"LKNE_JC": np.full((data.n_frames, 3), 12.5)}
    write_markers(tmp_path / "x.trc", data)
    read = read_markers(tmp_path / "x.trc")
    assert read.labels[-1] == "LKNE_JC"
    np.testing.assert_array_equal(read.positions[:, -1], data.extra["LKNE_JC"])
    assert read.flags[20, 3] == FLAG_OBSERVED


@pytest.mark.parametrize("name", ["lowerbody_clusters_knee_0401.c3d", "cmu_85_02.c3d"])
def test_c3d_to_trc_to_c3d(name: str, tmp_path: Path, real_file: Callable[[str], Path]) -> None:
    original = read_c3d(real_file(name))
    write_markers(tmp_path / "take.trc", original)
    via_trc = read_markers(tmp_path / "take.trc")
    write_markers(tmp_path / "take.c3d", via_trc)
    back = read_c3d(tmp_path / "take.c3d")
    for read in (via_trc, back):
        assert read.labels == original.labels
        assert read.rate == original.rate and read.first_frame == original.first_frame
        np.testing.assert_array_equal(as_float32(read.positions), original.positions)  # 9 digits hold a float32
        np.testing.assert_array_equal(read.flags, original.flags)
    np.testing.assert_array_equal(back.positions, original.positions)


def test_other_exporters_layout(tmp_path: Path) -> None:
    """Metres, CRLF, no blank line, trailing tabs, empty and NaN cells, rows cut short, 0,0,0 gaps, subject prefix."""
    text = (
        "PathFileType\t4\t(X/Y/Z)\tC:\\data\\trial.trc\r\n"
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames\r\n"
        "50.00\t50.00\t3\t2\tm\t50.00\t7\t3\r\n"
        "Frame#\tTime\tS1:HEAD\t\t\tS1:TOE\t\t\t\r\n"
        "\t\tX1\tY1\tZ1\tX2\tY2\tZ2\t\r\n"
        "7\t0.00\t1.0\t2.0\t3.0\t0.5\t0.25\t0.125\t\r\n"
        "8\t0.02\t1.5\t\t3.5\tNaN\tnan\tNaN\r\n"
        "9\t0.04\t0.0\t0.0\t0.0\t0.1\r\n"
    )
    path = tmp_path / "trial.trc"
    path.write_bytes(text.encode())
    data = read_trc(path)
    assert data.labels == ["HEAD", "TOE"] and data.rate == 50.0 and data.first_frame == 7
    missing = np.isnan(data.positions).any(axis=2)
    np.testing.assert_array_equal(missing, [[False, False], [True, True], [True, True]])
    assert np.isnan(data.positions[missing]).all()  # a sample with one empty coordinate is missing as a whole
    np.testing.assert_array_equal(data.positions[0], [[1000.0, 2000.0, 3000.0], [500.0, 250.0, 125.0]])
    np.testing.assert_array_equal(data.flags, np.where(missing, FLAG_MISSING, FLAG_OBSERVED))


def test_space_separated_file_and_rate_from_time(tmp_path: Path) -> None:
    text = (
        "PathFileType 4 (X/Y/Z) spaces.trc\n"
        "NumFrames NumMarkers Units\n"
        "2 2 mm\n"
        "Frame# Time A B\n"
        "X1 Y1 Z1 X2 Y2 Z2\n"
        "\n"
        "1 0.000 1 2 3 4 5 6\n"
        "2 0.004 7 8 9 10 11 12\n"
    )
    (tmp_path / "spaces.trc").write_text(text)
    data = read_trc(tmp_path / "spaces.trc")
    assert data.labels == ["A", "B"] and data.rate == pytest.approx(250.0)
    np.testing.assert_array_equal(data.positions.reshape(2, 6), [[1, 2, 3, 4, 5, 6], [7, 8, 9, 10, 11, 12]])


def test_a_tabbed_header_over_spaced_rows(tmp_path: Path) -> None:
    """Some exporters write the header with tabs and the frames with spaces: the rows read as the tabbed file's."""
    data = synthetic()
    data.positions[np.isnan(data.positions)] = 0.0  # spaced rows have no empty cells: missing as 0,0,0
    write_trc(tmp_path / "tabs.trc", data)
    lines = (tmp_path / "tabs.trc").read_text().split("\n")
    spaced = lines[:6] + ["  ".join(line.split("\t")) for line in lines[6:]]
    (tmp_path / "spaced.trc").write_text("\n".join(spaced))
    tabbed, read = read_trc(tmp_path / "tabs.trc"), read_trc(tmp_path / "spaced.trc")
    np.testing.assert_array_equal(read.positions, tabbed.positions)
    assert read.labels == tabbed.labels and np.isnan(read.positions[3:7, 1]).all()


def test_a_cell_that_is_no_number_is_named_by_row_and_column(tmp_path: Path) -> None:
    path = tmp_path / "bad.trc"
    path.write_text(HEADER.format(frames=2) + "1\t0\t1\t2\t3\n2\t0.01\t4\t" + "5e" * 100 + "\t6\n")
    with pytest.raises(MocapFileError) as raised:
        read_trc(path)
    message = str(raised.value)
    assert "frame row 2, column 4: '5e5e5e" in message and len(message) < len(str(path)) + 120


HEADER = (
    "PathFileType\t4\t(X/Y/Z)\tbad.trc\n"
    "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\n"
    "100\t100\t{frames}\t1\tmm\n"
    "Frame#\tTime\tA\t\t\n"
    "\t\tX1\tY1\tZ1\n\n"
)


@pytest.mark.parametrize(("content", "message"), [
    ("just some notes\nabout a trial\n", "not a TRC file"),
    (HEADER.format(frames=0), "no frames"),
    (HEADER.format(frames=5) + "1\t0\t1\t2\t3\n2\t0.01\t1\t2\t3\n", "truncated TRC file"),
    (HEADER.format(frames=1) + "1\t0\t1\tabc\t3\n", "not a number"),
    ("PathFileType\t4\t(X/Y/Z)\tbad.trc\nDataRate\n", "truncated or malformed"),
    (HEADER.format(frames=1).replace("mm", "furlong") + "1\t0\t1\t2\t3\n", "unknown length unit"),
])
def test_bad_files_name_themselves(content: str, message: str, tmp_path: Path) -> None:
    path = tmp_path / "bad.trc"
    path.write_text(content)
    with pytest.raises(MocapFileError, match=rf"bad\.trc: .*{message}"):
        read_markers(path)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(MocapFileError, match=r"gone\.trc: no such file"):
        read_trc(tmp_path / "gone.trc")


def test_synthetic_c3d_to_trc(tmp_path: Path) -> None:
    data = synthetic(first_frame=1)
    write_c3d(tmp_path / "s.c3d", data)
    write_trc(tmp_path / "s.trc", read_c3d(tmp_path / "s.c3d"))
    read = read_trc(tmp_path / "s.trc")
    np.testing.assert_array_equal(as_float32(read.positions), as_float32(data.positions))
    np.testing.assert_array_equal(read.flags, data.flags)
