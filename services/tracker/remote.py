"""The network stages seen from the tracker service: the detector (``rpc/detect``), yolo (``rpc/dynamics``) and
matcher (``rpc/match``) services asked over the bus, each job to one of their replicas (:mod:`twohr.replicas`: the
least busy; sent again to another if its replica goes away).

A tracker service gets its stages from a :class:`StageProvider`: the stack's tracker from :class:`RemoteStages`
(every network over the bus); a robot's own tracker composes its own (some networks in its process, the others
from a :class:`RemoteStages`: ``twohr_app.edge``)."""

from __future__ import annotations

from typing import Protocol

import numpy as np
import zenoh

from twohr import keys
from twohr.config import PipelineConfig
from twohr.dataset import Frame
from twohr.features import Keypoints, Matches
from twohr.messages import (
    DynamicsMsg,
    FrameMsg,
    KeypointsMsg,
    MatchesMsg,
    MatchRequestMsg,
    colour_image,
    decode,
    encode,
    split_matches,
)
from twohr.replicas import Replicas

from .stages import Stages


class StageProvider(Protocol):
    """Where a tracker service's sessions get their stages."""

    replicas: dict[str, Replicas]
    """the network services' replicas this provider asks, by service (the tracker's health counts their jobs)"""

    def open(self, session: zenoh.Session) -> None:
        """The tracker's bus session is open: follow the replicas on it."""

    def stages_for(self, header: FrameMsg, config: PipelineConfig) -> Stages:
        """The stages of a session's schedule, built on its first frame (``header``: its robot and camera)."""


class RemoteStage:
    """A network stage in another service, asked over the bus with the frame message as the source sent it: one
    replica of that service answers each job (:class:`twohr.replicas.Replicas`)."""

    def __init__(self, replicas: Replicas, robot_id: str, query: str, parse, timeout: float = 10.0,
                 upload=None) -> None:
        """``upload``: the frame message -> what is sent (default: the message itself)."""
        self.replicas, self.robot_id, self.query, self.parse = replicas, robot_id, query, parse
        self.timeout, self.upload = timeout, upload

    def __call__(self, frame: Frame):
        payload = frame.message if self.upload is None else self.upload(frame.message)
        return self.parse(self.replicas.call(self.robot_id, self.query, payload, self.timeout))


def keypoints_reply(payload: bytes) -> Keypoints:
    _, arrays = decode(payload, KeypointsMsg)
    return Keypoints(arrays["xy"], arrays["descriptors"], arrays["scores"], arrays.get("reliability"),
                     arrays.get("repeatability"))


def dynamics_reply(payload: bytes) -> tuple[np.ndarray, int]:
    message, arrays = decode(payload, DynamicsMsg, only=("mask",))
    return arrays["mask"].astype(bool), len(message.names)


class RemoteMatcher:
    """The match stage in the matcher service (one replica per job), for the frame it names."""

    def __init__(self, replicas: Replicas, robot_id: str, session_id: str, timeout: float = 10.0) -> None:
        self.replicas, self.robot_id, self.session_id, self.timeout = replicas, robot_id, session_id, timeout

    def __call__(self, frame: Frame, desc_a: np.ndarray, desc_b: np.ndarray) -> Matches:
        return self._ask(frame, "local map", {"desc_a": desc_a, "desc_b": desc_b})[0]

    def sets(self, frame: Frame, desc_a: np.ndarray, sets: list[np.ndarray]) -> list[Matches]:
        """Matches against several reference sets (a relocalisation's candidate keyframes) in one query."""
        sizes = np.array([len(desc_b) for desc_b in sets], np.int64)
        return self._ask(frame, "candidate keyframes", {"desc_a": desc_a, "desc_b": np.concatenate(sets),
                                                        "desc_b_sizes": sizes})

    def _ask(self, frame: Frame, reference: str, arrays: dict[str, np.ndarray]) -> list[Matches]:
        request = MatchRequestMsg(session_id=self.session_id, robot_id=self.robot_id, frame_index=frame.index,
                                  stamp=frame.stamp, reference=reference)
        answer = self.replicas.call(self.robot_id, keys.MATCH_QUERY, encode(request, arrays), self.timeout)
        _, found = decode(answer, MatchesMsg)
        return split_matches(Matches(found["idx_a"], found["idx_b"], found["scores"]), found.get("set_counts"))


class RemoteStages:
    """Every network asked over the bus, one replica per job (the stack's tracker). ``wait_for_one``: how long a
    job waits for a replica to appear (a replica restarting; a robot's own tracker waits less: past it, the link to
    the stack is taken as down and the job is skipped)."""

    def __init__(self, wait_for_one: float = 10.0) -> None:
        self.wait_for_one = wait_for_one
        self.replicas: dict[str, Replicas] = {}

    def open(self, session: zenoh.Session) -> None:
        self.replicas = {name: Replicas(session, name, wait_for_one=self.wait_for_one)
                         for name in keys.NETWORK_SERVICES}

    def stages_for(self, header: FrameMsg, config: PipelineConfig) -> Stages:
        robot_id = header.robot_id
        matcher = RemoteMatcher(self.replicas["matcher"], robot_id, header.session_id)
        # the detector reads the colour image alone: the depth image (half the message) stays here
        return Stages(RemoteStage(self.replicas["detector"], robot_id, keys.DETECT_QUERY, keypoints_reply,
                                  upload=colour_image),
                      RemoteStage(self.replicas["yolo"], robot_id, keys.DYNAMICS_QUERY, dynamics_reply)
                      if config.yolo.enabled else None, matcher, match_sets=matcher.sets)

    def bytes_sent(self) -> int:
        """The jobs' payloads sent so far, to every network."""
        return sum(replicas.bytes_sent for replicas in self.replicas.values())
