"""Every command that writes a file refuses, in one line and before any work, an output it cannot write."""

from __future__ import annotations

import tempfile
from pathlib import Path

import pytest

from mocapflow.cli import main


def unwritable_folder() -> Path:
    """A folder in which no file can be made, even by root: sysfs."""
    folder = Path("/sys")
    try:
        tempfile.TemporaryFile(dir=folder).close()
    except OSError:
        return folder
    pytest.skip("this machine has no folder that refuses files")


def test_an_output_in_a_folder_that_refuses_files_is_one_line(tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    folder = unwritable_folder()
    trial = tmp_path / "trial.c3d"
    assert main(["simulate", "-o", str(trial), "--frames", "300"]) == 0
    skeleton = tmp_path / "skeleton.json"
    capsys.readouterr()
    commands = [
        ["simulate", "-o", str(folder / "sim.c3d")],
        ["label", str(trial), "-o", str(folder / "labelled.c3d")],
        ["fill", str(trial), "-o", str(folder / "filled.c3d")],
        ["calibrate", str(trial), "-o", str(folder / "skeleton.json")],
        ["solve", str(trial), "--skeleton", str(skeleton), "-o", str(folder / "pose.csv")],
    ]
    for args in commands:
        assert main(args) == 2, args
        captured = capsys.readouterr()
        lines = captured.err.strip().splitlines()
        assert len(lines) == 1 and "cannot write there" in lines[0] and str(folder) in lines[0], (args, captured)
        assert "frames" not in captured.out, captured.out  # refused before reading or computing anything
    assert not (folder / "sim.c3d").exists()
