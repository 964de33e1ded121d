"""``mocapflow serve qtm|natnet FILE [--port P] [--speed X] [--loop]``: a stand-in tracker server speaking Qualisys
QTM's real-time protocol or OptiTrack's NatNet, playing a marker file in real time (or, for NatNet, a packet capture
of a real session), so that a graph can be tried or taught without the capture PC."""

from __future__ import annotations

import argparse
import asyncio
from pathlib import Path

from mocapflow.errors import MocapflowError

PORTS = {"qtm": 22223, "natnet": 1510}


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser("serve", help="stand-in QTM or NatNet server playing a marker file")
    parser.add_argument("protocol", choices=sorted(PORTS), help="qtm: QTM real-time protocol (TCP); natnet: NatNet 3 "
                        "(UDP unicast)")
    parser.add_argument("file", help="C3D or TRC file (natnet: also a .pcapng capture of a NatNet session)")
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    parser.add_argument("--port", type=int, default=None,
                        help="qtm: TCP port (default 22223); natnet: command port (default 1510)")
    parser.add_argument("--speed", type=float, default=1.0, help="time factor: 2 plays twice as fast")
    parser.add_argument("--loop", action="store_true", help="start again at the end (frame numbers keep rising)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from mocapflow.io.markers import read_markers

    if args.speed <= 0:
        raise MocapflowError(f"--speed must be positive, not {args.speed}")
    port = args.port or PORTS[args.protocol]
    path = Path(args.file)
    source: object
    try:
        if args.protocol == "natnet" and path.suffix.lower() in (".pcapng", ".pcap"):
            from mocapflow.trackers.natnet_server import Recording

            recording = Recording.read(path)
            what = f"{len(recording.frames)} recorded frames"
            source = recording
        else:
            data = read_markers(path)
            what = f"{len(data.positions)} frames x {len(data.labels)} markers at {data.rate:g} Hz"
            source = data
    except (OSError, ValueError) as exc:
        raise MocapflowError(str(exc)) from None

    def ready() -> None:
        print(f"mocapflow serve {args.protocol}: {path} ({what}) on {args.host}:{port}; starts with the first client",
              flush=True)

    try:
        asyncio.run(serve(args.protocol, source, path.stem, args, port, ready))
    except OSError as exc:
        raise MocapflowError(f"cannot listen on {args.host}:{port}: {exc.strerror or exc}") from None
    return 0


async def serve(protocol: str, source: object, name: str, args: argparse.Namespace, port: int, ready: object) -> None:
    if protocol == "qtm":
        from mocapflow.trackers.qtm_server import QtmServer

        await QtmServer(source, args.speed, args.loop).serve(args.host, port, ready)  # type: ignore[arg-type]
    else:
        from mocapflow.trackers.natnet_server import NatNetServer

        await NatNetServer(source, name, args.speed, args.loop, data_port=port + 1).serve(  # type: ignore[arg-type]
            args.host, port, ready)  # type: ignore[arg-type]
