"""BVH reading: a real CMU clip, hand-checked rotation orders, and malformed files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mocapflow.errors import MocapFileError
from mocapflow.io.bvh import read_bvh

CMU = Path(__file__).resolve().parents[2] / "shared" / "data" / "cmu_131_01.bvh"

# A two-bone arm: root with 6 channels, an elbow with Z-X-Y rotations, an end site 10 units along its x.
SMALL = """HIERARCHY
ROOT Base
{
\tOFFSET 0 0 0
\tCHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation
\tJOINT Elbow
\t{
\t\tOFFSET 0 5 0
\t\tCHANNELS 3 Zrotation Xrotation Yrotation
\t\tEnd Site
\t\t{
\t\t\tOFFSET 10 0 0
\t\t}
\t}
}
MOTION
Frames: 2
Frame Time: 0.01
1 2 3 0 0 0 0 0 0
1 2 3 90 0 0 90 90 0
"""


def write(tmp_path: Path, text: str, name: str = "x.bvh") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def test_small_file_follows_each_joints_channel_order(tmp_path: Path) -> None:
    bvh = read_bvh(write(tmp_path, SMALL))
    assert bvh.names == ["Base", "Elbow"] and list(bvh.parents) == [-1, 0] and bvh.frames == 2
    assert bvh.rate == pytest.approx(100.0) and bvh.channels[1] == ("Zrotation", "Xrotation", "Yrotation")
    np.testing.assert_array_equal(bvh.end_sites[1], [10, 0, 0])
    np.testing.assert_array_equal(bvh.root_translation, [[1, 2, 3], [1, 2, 3]])
    positions = bvh.forward_kinematics()
    np.testing.assert_allclose(positions[0], [[1, 2, 3], [1, 7, 3]])
    # Frame 1: the root turns 90 degrees about z, so the elbow offset (0, 5, 0) points along -x.
    np.testing.assert_allclose(positions[1], [[1, 2, 3], [-4, 2, 3]], atol=1e-12)
    # The elbow's rotation is Rz(90) @ Rx(90) (channel order, intrinsic), not Rx(90) @ Rz(90).
    expected = Rotation.from_euler("ZX", [90, 90], degrees=True).as_matrix()
    np.testing.assert_allclose(bvh.rotations[1, 1], expected, atol=1e-12)
    assert not np.allclose(expected, Rotation.from_euler("XZ", [90, 90], degrees=True).as_matrix())
    np.testing.assert_allclose(bvh.local_rotations(1).as_matrix(), bvh.rotations[:, 1])
    assert bvh.index("elbow") == 1


def test_cmu_clip_has_31_joints_994_frames_at_120_hz_and_rigid_bones() -> None:
    if not CMU.is_file():
        pytest.skip(f"real data file {CMU} is absent")
    bvh = read_bvh(CMU)
    assert len(bvh.names) == 31 and bvh.frames == 994 and bvh.rate == pytest.approx(120.0, rel=1e-4)
    assert bvh.names[0] == "Hips" and {"LeftKnee", "RightElbow", "Head"} <= set(bvh.names)
    assert bvh.rotations.shape == (994, 31, 3, 3) and bvh.translations.shape == (994, 31, 3)
    positions = bvh.forward_kinematics()
    child = np.arange(1, 31)
    bones = np.linalg.norm(positions[:, child] - positions[:, bvh.parents[child]], axis=-1)
    np.testing.assert_allclose(bones, np.broadcast_to(np.linalg.norm(bvh.offsets[child], axis=1), bones.shape),
                               atol=1e-9)
    assert np.ptp(positions[:, 0], axis=0).max() > 10  # the subject moves about
    # The rotations are proper and the first frame matches the file's first line.
    np.testing.assert_allclose(np.linalg.det(bvh.rotations), 1.0, atol=1e-9)
    first = CMU.read_text().split("Frame Time:")[1].split("\n")[1].split()
    np.testing.assert_allclose(bvh.root_translation[0], np.array(first[:3], float))
    hips = Rotation.from_euler("ZYX", np.array(first[3:6], float), degrees=True).as_matrix()
    np.testing.assert_allclose(bvh.rotations[0, 0], hips, atol=1e-12)


@pytest.mark.parametrize(
    "text, message",
    [
        ("", "no HIERARCHY and MOTION"),
        ("hello world", "no HIERARCHY and MOTION"),
        (SMALL.replace("1 2 3 90 0 0 90 90 0\n", "1 2 3 90\n"), "truncated or malformed BVH motion"),
        (SMALL.replace("Frames: 2", "Frames: two"), "frame count is 'two'"),
        (SMALL.replace("OFFSET 0 5 0", "OFFSET 0 five 0"), "offset is 'five'"),
        (SMALL.replace("Xrotation Yrotation\n", "Xrotation Wrotation\n"), "unknown channels"),
        (SMALL.replace("\t}\n}\nMOTION", "\t}\nMOTION"), "ends where"),
        (SMALL.replace("1 2 3 0 0 0", "1 2 x 0 0 0"), "non-numeric"),
        (SMALL.replace("Frame Time: 0.01", "Frame Time: 0"), "Frame Time: 0"),
    ],
)
def test_malformed_files_raise_one_line_errors(tmp_path: Path, text: str, message: str) -> None:
    path = write(tmp_path, text)
    with pytest.raises(MocapFileError, match=message) as info:
        read_bvh(path)
    assert "\n" not in str(info.value) and str(path) in str(info.value)


def test_missing_file_is_a_file_error(tmp_path: Path) -> None:
    with pytest.raises(MocapFileError, match="no such file"):
        read_bvh(tmp_path / "absent.bvh")
