"""Skeletons of every real full-body recording, calibrated with no option, checked against anatomy.

The marker-name -> body-region maps and the checks live in benchmarks/real_skeletons.py (which prints the same table
for the docs); calibration never sees them.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

from real_skeletons import FILES, check, region  # noqa: E402

from mocapflow.io.markers import read_markers  # noqa: E402
from mocapflow.mocap.calibration import calibrate  # noqa: E402


@pytest.mark.parametrize("name", FILES)
def test_real_recording_gives_an_anatomical_skeleton(name: str, real_file: Callable[[str], Path]) -> None:
    data = read_markers(real_file(name))
    skeleton = calibrate(data.positions, data.labels, data.rate, show_progress=False)
    checks = check(skeleton, data.positions, data.labels)
    assert not checks.mixed, f"segments mixing limbs, or a leg and the trunk: {checks.mixed}"
    assert not checks.not_chains, f"limbs that are not one chain hanging from the body: {checks.not_chains}"
    assert not checks.short_legs, f"legs without thigh, shank and foot: {checks.short_legs}"
    assert checks.fit_mm < 10.0
    used = {m for s in skeleton.segments for m in s.markers}
    assert len(used) >= 0.9 * len(data.labels)  # markers are left out only one by one, with a reason


def test_region_map_knows_each_file(real_file: Callable[[str], Path]) -> None:
    """The checks mean something only if every limb of each full-body file is mapped."""
    for name in FILES:
        labels = read_markers(real_file(name)).labels
        regions = {region(label) for label in labels}
        limbs = {"left leg", "right leg"} | ({"left arm", "right arm"} if "lowerbody" not in name else set())
        assert limbs <= regions, name
