"""``mocapflow view [GRAPH | PREFIX | FILE]``: a running graph, or a recording, as a Rerun 3D scene.

Live, the command joins the graph's Zenoh router with its own session and subscribes to the graph's streams, so a
viewer attaches from any machine of the lab without touching the graph: at a display rate (``--rate``, up to 60 Hz)
to their previews and the nodes' health, so that the graph sends it no more than it draws; at ``--rate 0`` to every
key under the graph's prefix. Each data stream is drawn under
``world/{node}/{output}``, node health under ``health/``. From an MCAP recording the same samples give the same scene;
from a C3D or TRC file, its markers (and joint centres, with bones when ``--skeleton`` is given).
"""

from __future__ import annotations

import argparse
import itertools
import os
import queue
import threading
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

from mocapflow.io.scene import UP_AXES
from mocapflow.runtime.session import DEFAULT_ENDPOINT
from mocapflow.runtime.signals import stop_on_signals

if TYPE_CHECKING:
    from mocapflow.io.markers import MarkerData
    from mocapflow.mocap.model import SkeletonModel

RECORDINGS = (".mcap", ".c3d", ".trc")
GRAPHS = (".yaml", ".yml")


def register(sub: argparse._SubParsersAction) -> None:
    v = sub.add_parser("view", help="show a running graph or a recording in Rerun's 3D viewer")
    v.add_argument("source", nargs="?", default="mocapflow",
                   help="graph file, key prefix of a running graph (default: every graph), or a .mcap, .c3d or "
                        ".trc recording")
    v.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                   help=f"router to join (default: the graph's, else {DEFAULT_ENDPOINT})")
    out = v.add_argument_group("where to show it (default: --spawn)")
    out.add_argument("--spawn", action="store_true", help="start Rerun's native viewer here")
    out.add_argument("--viewer", metavar="URL", help="a running Rerun viewer, e.g. rerun+http://HOST:9876/proxy")
    out.add_argument("--serve", action="store_true", help="serve the web viewer (open http://HOST:WEB_PORT)")
    out.add_argument("--save", metavar="PATH.rrd", help="write the scene to an .rrd file")
    v.add_argument("--grpc-port", type=int, default=9876, help="port of the spawned viewer or of the server")
    v.add_argument("--web-port", type=int, default=9090, help="web viewer port with --serve")
    v.add_argument("--memory-limit", default="1GiB", help="memory of the viewer or server (oldest data dropped)")
    v.add_argument("--up", choices=UP_AXES, help="up axis (default: the file's, else +Z)")
    v.add_argument("--rate", type=float, default=60.0, help="live display rate, Hz (0: every frame)")
    v.add_argument("--skeleton", metavar="SKELETON.json", help="C3D/TRC: skeleton for segment colours and bones")
    v.add_argument("--duration", type=float, metavar="S", help="live: stop after S seconds")
    v.set_defaults(func=_view)


def _view(args: argparse.Namespace) -> int:
    from mocapflow.errors import MocapflowError
    from mocapflow.io.scene import Scene, close_stream, open_stream, up_axis_of_file

    source = Path(args.source)
    suffix = source.suffix.lower()
    if suffix in RECORDINGS + GRAPHS and not source.is_file():
        raise MocapflowError(f"{source}: no such file")
    if args.rate < 0:
        raise MocapflowError("--rate must be 0 (every frame) or positive")
    if args.skeleton and suffix not in (".c3d", ".trc"):
        raise MocapflowError("--skeleton applies to a .c3d or .trc file")
    # Problems reach the user as one line of ours; RUST_LOG=warn shows Rerun's own log.
    os.environ.setdefault("RUST_LOG", "off")
    stop = threading.Event()
    # Read (and so check) the source before a viewer or file is opened.
    draw: Callable[[Scene], int]
    up_from: Path | None = None
    if suffix == ".mcap":
        draw = _recording(source)
    elif suffix in (".c3d", ".trc"):
        draw, up_from = _marker_file(source, args.skeleton), source
    else:
        prefix, connect = args.source.rstrip("/"), list(args.connect)
        if suffix in GRAPHS:
            prefix, graph_connect, up_from = _graph(source)
            connect = connect or graph_connect
        draw = partial(_live, prefix=prefix, connect=connect, rate=args.rate, duration=args.duration, stop=stop)
    up = args.up or (up_axis_of_file(up_from) if up_from else None)
    if up is None:
        print(f"up axis: +Z ({up_from or args.source} does not say; set --up otherwise)", flush=True)
        up = "+Z"
    try:
        stream = open_stream(source.stem if suffix else args.source,
                             spawn=args.spawn or not (args.viewer or args.serve or args.save), connect=args.viewer,
                             serve=args.serve, save=args.save, memory_limit=args.memory_limit,
                             grpc_port=args.grpc_port, web_port=args.web_port,
                             health=suffix not in (".c3d", ".trc"))
    except (RuntimeError, OSError) as exc:
        raise MocapflowError(f"cannot open the viewer: {exc}") from None
    with stop_on_signals(stop):
        count = draw(Scene(stream, up=up))
        if args.serve and suffix in RECORDINGS:
            print(f"serving on http://127.0.0.1:{args.web_port} (Ctrl-C to stop)", flush=True)
            stop.wait()
    problem = close_stream(stream)
    if problem:
        raise MocapflowError(f"the viewer did not receive the scene: {problem}")
    print(f"{count} marker frames drawn" + (f" to {args.save}" if args.save else ""), flush=True)
    return 0


def _graph(path: Path) -> tuple[str, list[str], Path | None]:
    """A graph's key prefix, the router its run listens on, and the marker file it replays (for the up axis)."""
    from mocapflow.runtime.graph import load_graph

    graph = load_graph(path)
    connect = list(graph.zenoh.connect) or list(graph.zenoh.listen) or [DEFAULT_ENDPOINT]
    replayed = [Path(n.config["path"]) for n in graph.nodes.values() if n.plugin == "c3d-replay"]
    replayed = [p if p.is_absolute() or p.is_file() else path.parent / p for p in replayed]
    return graph.key_prefix, connect, next((p for p in replayed if p.is_file()), None)


class _Streams:
    """Samples to scene: decodes by the encoding's message type, draws under the key's path below the prefix."""

    DATA = ("MarkerFrame", "Pose")

    def __init__(self, scene: Any, prefix: str, previews: bool = False) -> None:
        """``previews``: draw the streams' previews, under their streams' names; otherwise previews (a copy of the
        streams drawn whole) are passed over. Sampled copies (for model stages) are always passed over."""
        self.scene, self.prefix, self.previews = scene, prefix, previews
        self.frames = 0
        self.open: set[str] = set()
        self.ended = False

    def handle(self, key: str, encoding: str, payload: bytes, delete: bool, time_ns: int) -> None:
        from mocapflow.messages import MESSAGE_TYPES, SCHEMA_PREFIX, DecodeError, decode
        from mocapflow.runtime import keys

        kind = keys.copy_kind(key)
        if kind is not None:
            if kind != keys.PREVIEW or not self.previews:
                return
            key = keys.original(key)
        if delete:
            if key in self.open:
                self.open.discard(key)
                self.ended = not self.open
            return
        type_name = encoding.partition(f";{SCHEMA_PREFIX}")[2]
        if type_name not in MESSAGE_TYPES:
            return
        try:
            message = decode(payload, MESSAGE_TYPES[type_name])
        except DecodeError:
            return
        if type_name in self.DATA:
            self.open.add(key)
        path = "world/" + key[len(self.prefix):].strip("/") if key.startswith(self.prefix) else "world/" + key
        self.scene.log(path, message, time_ns)
        self.frames += type_name == "MarkerFrame"


def _recording(path: Path) -> Callable[[Any], int]:
    from mocapflow.io.recording import read_recording

    samples = read_recording(path)
    first = next(samples, None)  # a file that is not a recording fails here

    def draw(scene: Any) -> int:
        if first is None:
            return 0
        streams = _Streams(scene, first.key.rsplit("/", 2)[0])  # {prefix}/{node}/{output} or {prefix}/_stats/{node}
        for s in itertools.chain([first], samples):
            streams.handle(s.key, s.encoding, s.payload, s.delete, s.log_time_ns)
        return streams.frames

    return draw


def _marker_file(path: Path, skeleton_path: str | None) -> Callable[[Any], int]:
    """A C3D or TRC file's markers, flags and joint centres (its extra points) frame by frame; with a skeleton, the
    segment colours and the bones between the joint centres it names."""
    from mocapflow.errors import MocapflowError
    from mocapflow.io.markers import read_markers
    from mocapflow.mocap.model import SkeletonModel

    data = read_markers(path)
    model = None
    if skeleton_path:
        try:
            model = SkeletonModel.model_validate_json(Path(skeleton_path).read_text())
        except (OSError, ValueError) as exc:
            raise MocapflowError(f"{skeleton_path}: not a skeleton file: {str(exc).splitlines()[0]}") from None
    return partial(_draw_markers, data=data, model=model)


def _draw_markers(scene: Any, data: MarkerData, model: SkeletonModel | None) -> int:
    import numpy as np

    from mocapflow.messages import MarkerFrame, Pose, Skeleton

    if model is not None:
        scene.skeleton(Skeleton(frame=data.first_frame, capture_ns=0, skeleton=model))
    joints = list(data.extra)
    centres = np.stack([data.extra[j] for j in joints], axis=1) if joints else None
    none3, none4 = np.zeros((0, 3)), np.zeros((0, 4))
    for i in range(data.n_frames):
        frame, capture_ns = data.first_frame + i, round(i / data.rate * 1e9)
        flags = None if data.flags is None else data.flags[i]
        scene.markers("world/markers", MarkerFrame(frame=frame, capture_ns=capture_ns, rate=data.rate,
                                                   positions=data.positions[i], labels=data.labels, flags=flags))
        if centres is not None:
            scene.pose("world/pose", Pose(frame=frame, capture_ns=capture_ns, joint_names=joints,
                                          joint_centres=centres[i], segment_names=[], rotations=none4,
                                          translations=none3))
    return data.n_frames


def _live(scene: Any, *, prefix: str, connect: list[str], rate: float, duration: float | None,
          stop: threading.Event) -> int:
    """Draw the graph's streams until Ctrl-C, ``duration``, or the end of every data stream seen. Live, only the
    latest message of each data key is drawn at each display tick, so a slow viewer skips frames, never lags; at a
    display rate (up to 60 Hz) the streams' previews are drawn, so that the graph sends no more than that for it."""
    import zenoh
    import zenoh.ext as zext

    from mocapflow.runtime import keys
    from mocapflow.runtime.preview import PREVIEW_HZ
    from mocapflow.runtime.session import model_history, open_client

    inbox: queue.Queue[tuple[str, str, bytes, bool, int]] = queue.Queue()

    def on_sample(sample: zenoh.Sample) -> None:
        inbox.put((str(sample.key_expr), str(sample.encoding), sample.payload.to_bytes(),
                   sample.kind == zenoh.SampleKind.DELETE, time.time_ns()))

    previews = 0 < rate <= PREVIEW_HZ
    streams = _Streams(scene, prefix, previews)
    period = 1.0 / rate if rate else 0.0
    deadline = None if duration is None else time.monotonic() + duration
    history = model_history()
    with open_client(connect) as session:
        # models (segments, skeleton) come from the publishers' cache
        subscribers: list[Any]
        if previews:
            subscribers = [
                zext.declare_advanced_subscriber(session, f"{prefix}/**/{keys.PREVIEW}/**", on_sample,
                                                 history=history),
                session.declare_subscriber(keys.stats_key(f"{prefix}/**"), on_sample)]
        else:
            subscribers = [zext.declare_advanced_subscriber(session, f"{prefix}/**", on_sample, history=history)]
        print(f"viewing {prefix}/** (Ctrl-C to stop)", flush=True)
        latest: dict[str, tuple[str, str, bytes, bool, int]] = {}
        due = time.monotonic()
        while not stop.is_set() and not streams.ended and (deadline is None or time.monotonic() < deadline):
            try:
                item = inbox.get(timeout=max(0.0, min(due - time.monotonic(), 0.1)) if period else 0.1)
            except queue.Empty:
                item = None
            if item is not None:
                key, encoding = item[0], item[1]
                if period and not item[3] and encoding.endswith(("/MarkerFrame", "/Pose")):
                    latest[key] = item  # drawn at the next tick
                else:
                    if item[3] and key in latest:
                        streams.handle(*latest.pop(key))
                    streams.handle(*item)
            if period and time.monotonic() >= due:
                for pending in latest.values():
                    streams.handle(*pending)
                latest.clear()
                due = max(due + period, time.monotonic())
        for pending in latest.values():
            streams.handle(*pending)
        for subscriber in subscribers:
            subscriber.undeclare()
    return streams.frames
