"""A capture as a Rerun scene: markers coloured by segment and by how each sample was made, rays, joint centres,
bones, timelines and node health. The live sink, ``mocapflow view`` on a running graph and ``mocapflow view`` on a
recording all draw through this one class, so they show the same scene.

Entities (under a stream's path, e.g. ``world/markers``): ``Points3D`` markers with their labels, their colour and their
flag as class id; ``LineStrips3D`` ``.../rays`` from each single-camera ray's origin to the marker (or ``ray_length_mm``
along it); for a pose, ``.../joints`` (``Points3D`` labelled by joint) and ``.../bones`` (one two-point strip per bone,
between the joint centres of a segment's two ends). Node health goes to ``health/{latency_p50_ms,latency_p99_ms,rate_hz}
/{node}`` as ``Scalars``. Timelines: ``frame`` (tracker frame number) and ``capture_time`` (the frame's capture time).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import TYPE_CHECKING, Final

import numpy as np

from mocapflow.messages import MarkerFrame, Message, NodeStats, Pose, Segments, Skeleton
from mocapflow.mocap.flags import FillCase
from mocapflow.mocap.model import SkeletonModel

if TYPE_CHECKING:
    import rerun as rr
    import rerun.blueprint as rrb

FLUSH_TIMEOUT_S: Final = 10.0
"""How long a closing stream waits for its sinks: a viewer that went away must not hold a node or command forever."""
UP_AXES: Final = ("+Z", "+Y", "+X", "-Z", "-Y", "-X")
"""Up directions a scene can be drawn with (Rerun's right-handed view coordinates)."""

LOST: Final = (128, 128, 128)
"""A marker without a position in this frame, drawn where it was last seen."""
UNASSIGNED: Final = (235, 235, 235)
"""An observed marker of no known segment (or of an unlabelled point cloud)."""
FLAG_COLOURS: Final[dict[int, tuple[int, int, int]]] = {
    FillCase.KALMAN: (255, 215, 0),
    FillCase.ONE_MISSING: (255, 140, 0),
    FillCase.TWO_MISSING: (255, 100, 170),
    FillCase.VIA_JOINT: (230, 60, 200),
    FillCase.CONSTANT_ROTOR: (150, 90, 255),
    FillCase.RAY: (0, 225, 225),
    FillCase.LEARNT: (90, 200, 90),
    FillCase.POSTURE: (230, 80, 80),
}
"""Estimated samples, by how they were estimated (``FillCase``); observed ones take their segment's colour."""
OTHER_ESTIMATE: Final = (255, 170, 90)
"""An estimated sample of a case the filler does not name."""
SEGMENT_COLOURS: Final = (
    (31, 119, 180), (44, 160, 44), (140, 205, 90), (23, 190, 150), (120, 170, 235), (188, 189, 34),
    (70, 95, 210), (100, 225, 160), (60, 140, 110), (170, 200, 255), (20, 90, 60), (110, 130, 160),
)
"""Observed markers, one colour per segment (cool colours, apart from the warm ones of estimated samples)."""

MARKER_RADIUS_MM: Final = 8.0
JOINT_RADIUS_MM: Final = 14.0
BONE_RADIUS_MM: Final = 5.0
RAY_RADIUS_MM: Final = 1.5
JOINT_COLOUR: Final = (220, 40, 40)
BONE_COLOUR: Final = (90, 90, 115)


def _packed(rgb: np.ndarray) -> np.ndarray:
    """RGB rows as Rerun's packed 0xRRGGBBAA colours (opaque)."""
    rgb = np.asarray(rgb, dtype=np.uint32).reshape(-1, 3)
    return rgb[:, 0] << 24 | rgb[:, 1] << 16 | rgb[:, 2] << 8 | 0xFF


_BY_FLAG = _packed(np.array([LOST, UNASSIGNED] + [FLAG_COLOURS.get(f, OTHER_ESTIMATE) for f in range(2, 256)]))
_BY_SEGMENT = _packed(np.array(SEGMENT_COLOURS))
_JOINT_RGBA, _BONE_RGBA = (int(c) for c in _packed(np.array([JOINT_COLOUR, BONE_COLOUR])))


def marker_colours(flags: np.ndarray, segment_of: np.ndarray) -> np.ndarray:
    """Packed colours (0xRRGGBBAA): observed samples by segment (``segment_of`` -1 = none), estimated ones by flag,
    missing ones grey."""
    colours = _BY_FLAG[flags]
    known = (flags == FillCase.OBSERVED) & (segment_of >= 0)
    colours[known] = _BY_SEGMENT[segment_of[known] % len(_BY_SEGMENT)]
    return colours


def bones(skeleton: SkeletonModel) -> list[tuple[str, str]]:
    """Bones as (parent joint, child joint): a segment's bone runs from the joint attaching it to its parent to each
    joint attaching a child to it."""
    joint_of_child = {j.child: j.name for j in skeleton.joints}
    return [(joint_of_child[j.parent], j.name) for j in skeleton.joints if j.parent in joint_of_child]


def up_axis_of_file(path: str | Path) -> str | None:
    """The up direction a marker file declares, or None: C3D ``POINT:Y_SCREEN`` (the screen's vertical axis, as
    Vicon, Qualisys and Mokka write it); TRC files are OpenSim's format, whose convention is Y up."""
    from mocapflow.io.c3d import is_c3d
    from mocapflow.io.markers import read_markers

    path = Path(path)
    if not is_c3d(path):
        return "+Y" if path.suffix.lower() == ".trc" else None
    read_markers(path)  # checks the file before ezc3d opens it
    import ezc3d

    point = ezc3d.c3d(str(path), extract_forceplat_data=False)["parameters"]["POINT"]
    value = point.get("Y_SCREEN", {}).get("value")
    axis = str(value[0]).strip().upper() if value is not None and len(value) else ""
    return axis if axis in UP_AXES else None


class Scene:
    """Draws messages into a Rerun recording stream. Not thread-safe: call it from one thread."""

    def __init__(self, stream: rr.RecordingStream, up: str = "+Z", ray_length_mm: float = 4000.0) -> None:
        import rerun as rr

        if up not in UP_AXES:
            raise ValueError(f"up must be one of {', '.join(UP_AXES)}, got {up!r}")
        self.rr = rr
        self.stream = stream
        self.ray_length_mm = ray_length_mm
        sign, axis = up[0], up[1]
        coordinates = getattr(rr.ViewCoordinates, f"RIGHT_HAND_{axis}_{'UP' if sign == '+' else 'DOWN'}")
        self.stream.log("world", coordinates, static=True)
        self.stream.log("world", rr.AnnotationContext(
            [(int(c), c.name.lower().replace("_", " ")) for c in FillCase]), static=True)
        self.segment_of: dict[str, int] = {}
        self.bones: list[tuple[str, str]] = []
        self._layout_key: tuple[object, ...] | None = None
        self._layout: tuple[list[str], np.ndarray, list[str]] = ([], np.zeros(0, np.intp), [])
        self._last_seen: dict[str, np.ndarray] = {}  # stream path -> (N, 3) last known positions

    def _at(self, message: Message) -> None:
        self.stream.set_time("frame", sequence=message.frame)
        self.stream.set_time("capture_time", timestamp=np.datetime64(message.capture_ns, "ns"))

    def log(self, path: str, message: object, received_ns: int = 0) -> None:
        """Draw any message under ``path`` (a stream's entity path, or the node name for ``NodeStats``)."""
        if isinstance(message, MarkerFrame):
            self.markers(path, message)
        elif isinstance(message, Pose):
            self.pose(path, message)
        elif isinstance(message, Skeleton):
            self.skeleton(message)
        elif isinstance(message, Segments):
            self.segments(message)
        elif isinstance(message, NodeStats):
            self.stats(message, received_ns)

    def segments(self, message: Segments) -> None:
        self.segment_of = {label: i for i, s in enumerate(message.segments) for label in s.markers}

    def skeleton(self, message: Skeleton) -> None:
        self.bones = bones(message.skeleton)
        self._layout_key = None
        if not self.segment_of:
            self.segment_of = {label: i for i, s in enumerate(message.skeleton.segments) for label in s.markers}

    def markers(self, path: str, frame: MarkerFrame) -> None:
        rr = self.rr
        positions: np.ndarray = frame.positions
        present = np.isfinite(positions).all(axis=1)
        flags = np.array(frame.flags if frame.flags is not None else present, dtype=np.uint8)
        flags[~present] = FillCase.MISSING
        if frame.labels is not None:
            segment_of = np.array([self.segment_of.get(label, -1) for label in frame.labels], dtype=np.int64)
            # a labelled marker that is lost stays where it was last seen, greyed
            last = self._last_seen.get(path)
            if last is None or len(last) != len(positions):
                last = np.full_like(positions, np.nan)
            last[present] = positions[present]
            self._last_seen[path] = last
            shown = np.isfinite(last).all(axis=1)
            xyz = last[shown]
            labels: list[str] | None = [label for label, s in zip(frame.labels, shown, strict=True) if s]
        else:
            segment_of = np.full(len(positions), -1, dtype=np.int64)
            shown = present
            xyz = positions[present]
            labels = None
        self._at(frame)
        self.stream.log(path, rr.Points3D(
            xyz, colors=marker_colours(flags[shown], segment_of[shown]), labels=labels,
            class_ids=flags[shown].astype(np.uint16), radii=MARKER_RADIUS_MM))
        if frame.rays is not None:
            self._rays(path, frame, positions)

    def _rays(self, path: str, frame: MarkerFrame, positions: np.ndarray) -> None:
        rays = np.asarray(frame.rays)
        has = np.isfinite(rays).all(axis=1)
        origin, direction = rays[has, :3], rays[has, 3:]
        end = positions[has]
        unknown = ~np.isfinite(end).all(axis=1)
        end[unknown] = origin[unknown] + self.ray_length_mm * direction[unknown]
        strips = np.stack([origin, end], axis=1)
        self.stream.log(f"{path}/rays", self.rr.LineStrips3D(
            strips, colors=FLAG_COLOURS[FillCase.RAY], radii=RAY_RADIUS_MM))

    def pose(self, path: str, pose: Pose) -> None:
        rr = self.rr
        centres = np.asarray(pose.joint_centres, dtype=float).reshape(-1, 3)
        self._at(pose)
        known = np.isfinite(centres).all(axis=1)
        names, ends, bone_names = self._pose_layout(pose.joint_names, known)
        self.stream.log(f"{path}/joints", rr.Points3D(
            centres[known], labels=names, show_labels=False, colors=np.full(len(names), _JOINT_RGBA, np.uint32),
            radii=np.full(len(names), JOINT_RADIUS_MM, np.float32)))
        self.stream.log(f"{path}/bones", rr.LineStrips3D(
            centres[ends].reshape(-1, 2, 3), labels=bone_names, show_labels=False,
            colors=np.full(len(bone_names), _BONE_RGBA, np.uint32),
            radii=np.full(len(bone_names), BONE_RADIUS_MM, np.float32)))

    def _pose_layout(self, joint_names: list[str], known: np.ndarray) -> tuple[list[str], np.ndarray, list[str]]:
        """The joints with a centre, the rows of the centres each bone joins (flat: its two ends in turn) and the
        bones' names, for these joints and this mask of known centres (kept: they change only with the mask)."""
        key = (tuple(joint_names), known.tobytes())
        if self._layout_key != key:
            row = {n: i for i, n in enumerate(joint_names) if known[i]}
            pairs = [(a, b) for a, b in self.bones if a in row and b in row]
            ends = np.array([row[n] for pair in pairs for n in pair], dtype=np.intp)
            self._layout = ([n for n in joint_names if n in row], ends, [f"{a} → {b}" for a, b in pairs])
            self._layout_key = key
        return self._layout

    def stats(self, stats: NodeStats, received_ns: int) -> None:
        """A node's latency and rate on the capture-time timeline, at the moment they were received."""
        self.stream.reset_time()
        self.stream.set_time("capture_time", timestamp=np.datetime64(received_ns, "ns"))
        for name in ("latency_p50_ms", "latency_p99_ms", "rate_hz"):
            value = getattr(stats, name)
            if value is not None:
                self.stream.log(f"health/{name}/{stats.node}", self.rr.Scalars(value))


def blueprint(health: bool) -> rrb.Blueprint:
    """The layout: the 3D scene, with node latency and rate as time series beside it when ``health`` is shown."""
    import rerun.blueprint as rrb

    scene = rrb.Spatial3DView(origin="world", name="capture")
    if not health:
        return rrb.Blueprint(scene, collapse_panels=True)
    return rrb.Blueprint(rrb.Horizontal(
        scene, rrb.Vertical(rrb.TimeSeriesView(origin="health/latency_p99_ms", name="latency p99 (ms)"),
                            rrb.TimeSeriesView(origin="health/rate_hz", name="rate (Hz)")),
        column_shares=[3, 1]), collapse_panels=True)


def open_stream(name: str, *, spawn: bool = False, connect: str | None = None, serve: bool = False,
                save: str | None = None, memory_limit: str = "1GiB", grpc_port: int = 9876,
                web_port: int = 9090, health: bool = False) -> rr.RecordingStream:
    """A Rerun recording stream to any of: a viewer spawned here, a viewer at ``connect`` (its gRPC URL), a gRPC
    server on ``grpc_port`` with the web viewer on ``web_port``, an .rrd file. ``memory_limit`` bounds the spawned
    viewer and the server: beyond it the oldest data is dropped, so a session of hours runs in bounded memory.
    ``health``: lay out node latency and rate beside the scene."""
    try:
        import rerun as rr
    except ImportError:
        raise RuntimeError("Rerun is not installed: pip install 'mocapflow[viewer]'") from None

    if not (spawn or connect or serve or save):
        raise ValueError("nowhere to show the scene: choose spawn, connect, serve or save")
    stream = rr.RecordingStream("mocapflow-" + re.sub(r"[^A-Za-z0-9_-]+", "-", name))
    sinks: list[rr.sinks.LogSinkLike] = []
    if spawn:
        stream.spawn(port=grpc_port, connect=False, memory_limit=memory_limit)
        sinks.append(rr.GrpcSink(f"rerun+http://127.0.0.1:{grpc_port}/proxy"))
    if connect:
        sinks.append(rr.GrpcSink(connect))
    if serve:
        server = rr.GrpcServerSink(port=grpc_port, server_memory_limit=memory_limit)
        sinks.append(server)
    if save:
        Path(save).parent.mkdir(parents=True, exist_ok=True)
        sinks.append(rr.FileSink(save))
    stream.set_sinks(*sinks, default_blueprint=blueprint(health))
    if serve:
        rr.serve_web_viewer(web_port=web_port, open_browser=False, connect_to=server.uri)
    return stream


def close_stream(stream: rr.RecordingStream) -> str | None:
    """Send what is pending (waiting at most ``FLUSH_TIMEOUT_S``) and close; the reason on one line if a sink could
    not take it (a viewer that went away), else None."""
    try:
        stream.flush(timeout_sec=FLUSH_TIMEOUT_S)
    except RuntimeError as exc:
        return str(exc).splitlines()[0]
    finally:
        stream.disconnect()
    return None
