"""``twohr camera``: the camera driver. Publishes RGB-D frames on ``twohr/<robot>/camera`` as a live camera does.

``--replay SEQ`` plays a recorded TUM-layout sequence at a fixed frame rate (the stand-in for a
camera in tests and demos); ``--realsense`` streams an Intel RealSense (``pip install
'twohr[realsense]'``) with depth aligned to colour. Every frame is a ``twohr.Frame`` message
(``twohr.messages.FrameMsg``) with the intrinsics and the depth scale (``camera.depth_factor``,
depth units per metre) in its header; the source service relays it into a live session.
"""

from __future__ import annotations

import argparse
import logging
import time
from collections.abc import Iterator
from pathlib import Path

from twohr.bus import add_router_option
from twohr.errors import TwohrError
from twohr.rates import ReplayPacer

log = logging.getLogger(__name__)


def camera_bus(args: argparse.Namespace):
    """How the camera joins the bus: a client config file (``--zenoh-config``), or a robot's bundle (``--keys``), or
    the default (``$TWOHR_ZENOH_ROUTER``, else ``tcp/127.0.0.1:7447``, with the credentials in the environment), to
    ``--router`` where given."""
    from twohr.bus import BusConfig, bus_from_args

    if args.zenoh_config:
        if not Path(args.zenoh_config).is_file():
            raise TwohrError(f"Zenoh config not found: {args.zenoh_config}")
        return BusConfig(config_file=args.zenoh_config)
    return bus_from_args(args).model_copy(update={"shared_memory": False})  # a client that comes and goes


def open_bus(args: argparse.Namespace):
    """A Zenoh session as :func:`camera_bus` says."""
    from twohr.bus import open_session

    return open_session(camera_bus(args))


def replay_payloads(sequence_dir: str, robot: str, rate: float, frames: int | None, start: int,
                    loop: bool = False) -> Iterator[bytes]:
    """Encoded frame messages of a recorded sequence, paced at ``rate`` frames per second. ``loop`` plays it
    again and again (for soak runs), each pass stamped after the one before; ``frames`` then counts over all
    passes. A missing or broken sequence raises :class:`TwohrError` at once, before any frame."""
    import numpy as np

    from twohr.dataset import RGBDSequence

    sequence = RGBDSequence(sequence_dir)
    if not 0 <= start < len(sequence):
        raise TwohrError(f"--start {start} is outside the sequence's {len(sequence)} frames")
    stamps = sequence.stamps[start:]
    period = float(stamps[-1] - stamps[0]) + (float(np.median(np.diff(stamps))) if len(stamps) > 1 else 1 / 30)
    return _replay(sequence, robot, ReplayPacer(fps=rate), frames, start, period if loop else None)


def _replay(sequence, robot: str, pacer: ReplayPacer, frames: int | None, start: int,
            period: float | None) -> Iterator[bytes]:
    from twohr.keys import LIVE_SESSION
    from twohr_services.source.core import frame_payloads

    sent, offset = 0, 0.0
    while frames is None or sent < frames:
        remaining = None if frames is None else frames - sent
        for item in frame_payloads(sequence, LIVE_SESSION, robot, start=start, max_frames=remaining,
                                   pace=pacer.wait, stamp_offset=offset):
            sent += 1
            yield item.payload
        if period is None:
            return
        offset += period


def realsense_payloads(robot: str, width: int, height: int, fps: int, frames: int | None) -> Iterator[bytes]:
    """Frames from the first Intel RealSense: depth aligned to colour, intrinsics and depth scale from the device.
    Raises :class:`TwohrError` at once when pyrealsense2 or the camera is missing."""
    try:
        import pyrealsense2 as rs
    except ImportError:
        raise TwohrError("pyrealsense2 is not installed: pip install 'twohr[realsense]'") from None
    if len(rs.context().query_devices()) == 0:
        raise TwohrError("no RealSense camera found: check the USB cable and permissions (udev rules)")
    return _realsense_stream(rs, robot, width, height, fps, frames)


def _realsense_stream(rs, robot: str, width: int, height: int, fps: int, frames: int | None) -> Iterator[bytes]:
    import numpy as np

    from twohr.dataset import CameraIntrinsics
    from twohr.keys import LIVE_SESSION
    from twohr.messages import FrameMsg, encode

    pipeline, config = rs.pipeline(), rs.config()
    config.enable_stream(rs.stream.color, width, height, rs.format.rgb8, fps)
    config.enable_stream(rs.stream.depth, width, height, rs.format.z16, fps)
    try:
        profile = pipeline.start(config)
    except RuntimeError as exc:
        raise TwohrError(f"cannot start the RealSense at {width}x{height} {fps} Hz: {exc}") from None
    try:
        depth_scale = profile.get_device().first_depth_sensor().get_depth_scale()  # metres per depth unit
        intr = profile.get_stream(rs.stream.color).as_video_stream_profile().get_intrinsics()
        opencv_model = intr.model == rs.distortion.brown_conrady and any(intr.coeffs)
        camera = CameraIntrinsics(fx=intr.fx, fy=intr.fy, cx=intr.ppx, cy=intr.ppy, width=intr.width,
                                  height=intr.height, depth_factor=1.0 / depth_scale,
                                  distortion=list(intr.coeffs)[:5] if opencv_model else [])
        align = rs.align(rs.stream.color)
        index = 0
        while frames is None or index < frames:
            aligned = align.process(pipeline.wait_for_frames())
            color, depth = aligned.get_color_frame(), aligned.get_depth_frame()
            if not color or not depth:
                continue
            message = FrameMsg(session_id=LIVE_SESSION, robot_id=robot, frame_index=index,
                               stamp=color.get_timestamp() / 1000.0, camera=camera, sent_at=time.time())
            arrays = {"rgb": np.asanyarray(color.get_data()), "depth": np.asanyarray(depth.get_data())}
            yield encode(message, arrays, {"rgb": "jpeg", "depth": "png"})
            index += 1
    finally:
        pipeline.stop()


def _camera(args: argparse.Namespace) -> int:
    from twohr import keys
    from twohr.identity import load_identity
    from twohr.service import declare_publisher

    if args.keys and args.zenoh_config:
        raise TwohrError("give --keys or --zenoh-config, not both")
    robot = args.robot or (load_identity(args.keys).name if args.keys else "robot1")
    try:
        key = keys.key(robot, keys.RAW_CAMERA)
    except ValueError as exc:
        raise TwohrError(str(exc)) from None
    if args.frames is not None and args.frames < 1:
        raise TwohrError("--frames must be at least 1")
    if args.rate < 0:
        raise TwohrError("--rate must be 0 (as fast as possible) or a frame rate in Hz")
    if args.linger < 0:
        raise TwohrError("--linger must be 0 or more seconds")
    if args.edge:
        from ..edge import parse_server_stages

        server_stages = parse_server_stages(args.server_stages)
    if args.replay:
        payloads = replay_payloads(args.replay, robot, args.rate, args.frames, args.start, args.loop)
    else:
        payloads = realsense_payloads(robot, args.width, args.height, args.fps, args.frames)
    if args.edge:
        from ..edge import run_edge

        known = None
        if args.replay:
            from twohr.dataset import RGBDSequence

            known = RGBDSequence(args.replay).camera
        return run_edge(camera_bus(args), robot, payloads, server_stages, args.linger, camera=known,
                        say=lambda line: print(line, flush=True))
    session = open_bus(args)
    sent, sent_bytes, t0 = 0, 0, time.monotonic()
    try:
        publisher = declare_publisher(session, key)
        for payload in payloads:
            publisher.put(payload)
            sent, sent_bytes = sent + 1, sent_bytes + len(payload)
        elapsed = max(time.monotonic() - t0, 1e-9)
        print(f"published {sent} frames on {key} in {elapsed:.1f} s ({sent / elapsed:.1f} FPS), {sent_bytes} bytes "
              f"({sent_bytes / elapsed:.0f} bytes/s upstream)")
    finally:
        session.close()
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("camera", help="camera driver: publish RGB-D frames on twohr/<robot>/camera",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument("--replay", metavar="SEQ", help="play a recorded TUM-layout sequence as a camera would")
    source.add_argument("--realsense", action="store_true", help="stream the first Intel RealSense camera")
    p.add_argument("--robot", default=None, help="robot id: frames go to twohr/<robot>/camera (default: the --keys "
                   "bundle's robot, else robot1)")
    p.add_argument("--rate", type=float, default=30.0, help="replay frame rate in Hz; 0 = as fast as possible "
                   "(default 30)")
    p.add_argument("--frames", type=int, default=None, help="stop after N frames (default: all / until Ctrl-C)")
    p.add_argument("--start", type=int, default=0, help="replay from this frame index (default 0)")
    p.add_argument("--loop", action="store_true", help="replay the sequence again and again, stamps going on in "
                   "time (for soak runs; stop with --frames or Ctrl-C)")
    p.add_argument("--zenoh-config", metavar="FILE.json5", help="Zenoh client configuration to open the session "
                   "from (default: connect to $TWOHR_ZENOH_ROUTER or tcp/127.0.0.1:7447)")
    add_router_option(p, help="router endpoint to connect to, instead of --zenoh-config (default: the --keys "
                      "bundle's endpoint, else $TWOHR_ZENOH_ROUTER)")
    p.add_argument("--edge", action="store_true", help="track on this host: the robot's own tracker runs in this "
                   "process and no frame leaves it (poses, paths and status go out as the stack's tracker sends them; "
                   "a fleet's robot needs a bundle of twohr keys add --edge; a stack without keys, a tracker's "
                   "--zenoh-config)")
    p.add_argument("--server-stages", default="detector", metavar="LIST", help="with --edge: the networks the stack "
                   "runs for this robot's keyframes, comma-separated (detector, yolo, matcher, or none); the others "
                   "run here (default: detector)")
    p.add_argument("--linger", type=float, default=120.0, metavar="S", help="with --edge: after the last frame, how "
                   "long to wait for the session's stop (DELETE /sessions/ID) before ending it here; either way its "
                   "refined trajectory goes out (default 120)")
    p.add_argument("--width", type=int, default=640, help="RealSense stream width (default 640)")
    p.add_argument("--height", type=int, default=480, help="RealSense stream height (default 480)")
    p.add_argument("--fps", type=int, default=30, help="RealSense frame rate (default 30)")
    p.set_defaults(func=_camera)
