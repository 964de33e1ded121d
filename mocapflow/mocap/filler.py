"""The occlusion filler's former import path: everything lives in ``mocapflow.mocap.filling``."""

from mocapflow.mocap.filling import (
    FillCase,
    FillerConfig,
    FillResult,
    GapFiller,
    fill_sequence,
    is_complete,
    nearest_on_circle,
    project_on_rays,
)

__all__ = ["FillCase", "FillResult", "FillerConfig", "GapFiller", "fill_sequence", "is_complete", "nearest_on_circle",
           "project_on_rays"]
