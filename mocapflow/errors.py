"""Errors a user can act on: each prints as one line and maps to a non-zero exit code."""


class MocapflowError(Exception):
    """Base class for every error mocapflow reports to a user."""


class MocapFileError(MocapflowError):
    """A file is missing, is not in the format its name claims, is truncated, or holds no usable data."""


class CalibrationError(MocapflowError):
    """The data cannot support the requested model (too few frames, markers, or range of motion)."""


class GraphError(MocapflowError):
    """A graph file is malformed or inconsistent; the message names the node and the field."""


class MotionError(MocapflowError):
    """A motion (a BVH recording) cannot drive the rig it is given to."""
