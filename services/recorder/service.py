"""The recorder service: every stream of every recorded session into ``<recordings>/<session>.mcap``.

A session's file opens on its ``start`` control message (when ``record`` is true) and is finalised after
``stop``: once the tracker's refined trajectory (the final ``path``) is in, for a session that has poses (at
most ``final_path_wait`` seconds later), otherwise after a short grace. Files of sessions still open when the
service exits are finalised too. A session's file stops growing at ``max_session_bytes`` (it is finalised there,
and the session's status says so). At start, files that a killed recorder left unfinalised are recovered
(``twohr.mcapfile.recover``): their readable prefix is re-indexed and marked partial.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

from twohr import keys
from twohr.bus import BusConfig, bus_from_args
from twohr.mcapfile import recover
from twohr.messages import ControlMsg, MergeMsg, MessageError, PathMsg, decode, split
from twohr.service import Service, one_line_errors, service_parser

from .core import RecordingOptions, SessionRecorder


class RecorderService(Service):
    name = "recorder"
    priority = "background"  # recording can lag a little; nothing waits for it

    def __init__(self, bus: BusConfig | None = None, recordings: Path = Path("recordings"),
                 grace: float = 1.0, options: RecordingOptions | None = None, max_session_bytes: int = 4 << 30,
                 final_path_wait: float = 30.0) -> None:
        super().__init__(bus, queue_size=256, policy="backpressure")
        self.recordings = recordings
        self.options = options or RecordingOptions()
        self.grace = grace
        self.final_path_wait = final_path_wait
        self.posed: set[str] = set()  # open sessions with a pose recorded: the tracker will send a final path
        self.max_session_bytes = max_session_bytes
        self.open: dict[str, SessionRecorder] = {}
        self.sharing: dict[str, str] = {}  # sessions that share a map: its name
        self.closing: dict[str, float] = {}
        self.owners: dict[str, str] = {}  # session -> the robot its start named, while its file is open

    def on_start(self) -> None:
        for path in sorted(self.recordings.glob("*.mcap")):
            kept = recover(path)
            if kept is not None:
                self.log.warning("recovered %s, left unfinalised by a crash: %d messages kept", path, kept)

    def subscriptions(self) -> list[str]:
        # and the merges of shared maps, in the recording of every session that shares the map
        return [keys.all_robots(stream) for stream in (*keys.STREAMS, keys.CONTROL)] + [keys.merged_key()]

    def handle(self, key: str, payload: bytes) -> None:
        _, stream = keys.parse(key)
        now = time.time_ns()
        if stream == keys.CONTROL:
            control, _ = decode(payload, ControlMsg)
            if control.command == "start" and control.map_mode.shared:
                self.sharing[control.session_id] = control.map_name
            if control.command == "start" and control.record:
                self._close(control.session_id)
                options = self.options.model_copy(update={
                    "record_descriptors": self.options.record_descriptors or control.record_descriptors,
                    "record_frames": self.options.record_frames or control.record_frames})
                self.open[control.session_id] = SessionRecorder(self.recordings / f"{control.session_id}.mcap",
                                                                options)
                self.owners[control.session_id] = control.robot_id
            recorder = self.open.get(control.session_id)
            if recorder is not None:
                recorder.write(key, payload, now)
            if control.command == "stop" and recorder is not None:
                # messages on other keys may still be in flight (Zenoh orders per key, not across keys), and the
                # refined trajectory comes after the stop
                wait = self.final_path_wait if control.session_id in self.posed else self.grace
                self.closing[control.session_id] = time.monotonic() + wait
            return
        message, _ = split(payload)
        if isinstance(message, MergeMsg):
            for session_id, name in self.sharing.items():
                if name == message.map_name and session_id in self.open:
                    self.open[session_id].write(key, payload, now)
            return
        recorder = self.open.get(message.session_id)
        if recorder is not None and self.owners.get(message.session_id) != message.robot_id:
            # a session id is no secret: the key (checked against the header) says which robot sent this
            raise MessageError(f"robot {message.robot_id!r} spoke for session {message.session_id}")
        if recorder is not None:
            recorder.write(key, payload, now)
            if stream == "pose":
                self.posed.add(message.session_id)
            elif isinstance(message, PathMsg) and message.final and message.session_id in self.closing:
                self.closing[message.session_id] = time.monotonic() + self.grace
            if recorder.file.tell() > self.max_session_bytes:
                self.log.warning("session %s reached %d bytes: its recording ends here", message.session_id,
                                 self.max_session_bytes)
                self.report(message, "capped", f"recording capped at {self.max_session_bytes} bytes")
                self._close(message.session_id)

    def process_one(self, timeout: float = 0.2) -> bool:
        handled = super().process_one(timeout)
        now = time.monotonic()
        for session_id in [s for s, due in self.closing.items() if due <= now]:
            self._close(session_id)
        return handled

    def _close(self, session_id: str) -> None:
        self.closing.pop(session_id, None)
        self.sharing.pop(session_id, None)
        self.posed.discard(session_id)
        recorder = self.open.get(session_id)
        if recorder is not None:
            recorder.close()
            del self.open[session_id]  # only now: a session not in ``open`` has a complete, indexed file
            self.owners.pop(session_id, None)
            self.log.info("finalised %s (%s)", recorder.path, recorder.counts)

    def run(self, stop=None) -> None:
        try:
            super().run(stop)
        finally:
            for session_id in list(self.open):
                self._close(session_id)


@one_line_errors("recorder")
def main(argv: list[str] | None = None) -> None:
    parser = service_parser("recorder", __doc__)
    parser.add_argument("--recordings", default="recordings", help="folder for the MCAP files")
    parser.add_argument("--max-session-gb", type=float, default=4.0, help="a session's recording ends at this size")
    parser.add_argument("--record-descriptors", action="store_true",
                        help="keep the raw keypoint descriptors in every recording (large; a session can ask too)")
    parser.add_argument("--record-frames", action="store_true",
                        help="keep the raw RGB-D frames verbatim in every recording, for exact replay (large)")
    args = parser.parse_args(argv)
    recordings = Path(args.recordings)
    if problem := unwritable(recordings):
        parser.exit(2, f"recorder: error: {problem}\n")
    bus = bus_from_args(args)
    options = RecordingOptions(record_descriptors=args.record_descriptors, record_frames=args.record_frames)
    RecorderService(bus, recordings, options=options,
                    max_session_bytes=int(args.max_session_gb * (1 << 30))).run_forever()


def unwritable(folder: Path) -> str | None:
    """Why the recorder could not write MCAP files into ``folder`` (None if it can). Checked at start,
    so that a wrongly owned volume is one clear line in the log, not a failed session later."""
    try:
        folder.mkdir(parents=True, exist_ok=True, mode=0o700)  # made here: private, as the files in it
    except OSError as exc:
        return f"cannot create the recordings folder {folder}: {exc.strerror}"
    if not os.access(folder, os.W_OK | os.X_OK):
        return (f"the recordings folder {folder} is not writable by uid {os.getuid()} "
                f"(owner uid {folder.stat().st_uid}); chown it, or in docker compose set TWOHR_UID=$(id -u)")
    return None
