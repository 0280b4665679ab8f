"""The matcher service: answers match queries on ``twohr/<robot>/rpc/match/<replica>`` and publishes each result
on ``twohr/<robot>/matches``.

The tracker asks it to match the current frame's descriptors against its local map, so the
learned matcher runs in its own process (and can be moved to a GPU box) while the tracker
keeps the map.
"""

from __future__ import annotations

import functools
import time

import numpy as np

from twohr import keys
from twohr.config import MatcherConfig
from twohr.messages import MatchesMsg, MatchRequestMsg, MessageError, decode, encode, joined_matches
from twohr.service import MODEL_CACHE_SIZE, Service, reply_to, serve

from .core import build_matcher

#: descriptor pairs one query may ask to compare (Na x Nb): a keyframe's 1500 against a local map of 5000 are 7.5 M
MAX_MATCH_PAIRS = 75_000_000


class MatcherService(Service):
    """Siamese (or baseline) matching as a query/reply service, with each session's matcher config."""

    name = "matcher"
    priority = "keyframe"  # the map's work: an equal share of the CPU, never less
    follows_sessions = True

    def __init__(self, bus=None) -> None:
        super().__init__(bus, queue_size=16, policy="backpressure")
        # one matcher per distinct config, shared by sessions; a few at most
        self.matcher_for = functools.lru_cache(maxsize=MODEL_CACHE_SIZE)(
            lambda conf_json: build_matcher(MatcherConfig.model_validate_json(conf_json)))
        self.queryable = None

    def on_start(self) -> None:
        self.queryable = self.declare_replica_queryable(keys.MATCH_QUERY)
        descriptors = np.zeros((8, 128), np.float32)
        descriptors[:, 0] = 1.0
        default = MatcherConfig().model_dump_json()
        self.warm_up("the matcher", lambda: self.matcher_for(default)(descriptors, descriptors))

    def handle(self, key: str, query) -> None:
        reply_to(query, self._match)

    def _match(self, payload: bytes) -> bytes:
        request, arrays = decode(payload, MatchRequestMsg)
        match = self.matcher_for(self.config_for(request.session_id).matcher.model_dump_json())
        t0 = time.perf_counter()
        desc_a, desc_b = arrays["desc_a"], arrays["desc_b"]
        check_pair(desc_a, desc_b)
        if "desc_b_sizes" in arrays:  # several reference sets, each matched apart
            sizes = np.asarray(arrays["desc_b_sizes"], np.int64)
            if sizes.ndim != 1 or (sizes < 0).any() or int(sizes.sum()) != len(desc_b):
                raise MessageError(f"desc_b_sizes {sizes.tolist()} do not add up to desc_b's {len(desc_b)} rows")
            found = joined_matches([match(desc_a, b) for b in np.split(desc_b, np.cumsum(sizes)[:-1])])
        else:
            matches = match(desc_a, desc_b)
            found = {"idx_a": matches.idx_a.astype("int64"), "idx_b": matches.idx_b.astype("int64"),
                     "scores": matches.scores.astype("float32")}
        reply = MatchesMsg(session_id=request.session_id, robot_id=request.robot_id, frame_index=request.frame_index,
                           stamp=request.stamp, reference=request.reference,
                           elapsed_ms=(time.perf_counter() - t0) * 1000)
        data = encode(reply, found)
        self.publish(keys.key(request.robot_id, "matches"), data)
        return data


def check_pair(desc_a: np.ndarray, desc_b: np.ndarray) -> None:
    """:class:`MessageError` unless two sets of descriptors can be matched within :data:`MAX_MATCH_PAIRS`: rows of
    one width and dtype (a mutual nearest neighbour builds the whole Na x Nb matrix)."""
    if desc_a.ndim != 2 or desc_b.ndim != 2 or desc_a.shape[1] != desc_b.shape[1] or desc_a.dtype != desc_b.dtype:
        raise MessageError(f"descriptors {desc_a.shape} {desc_a.dtype} and {desc_b.shape} {desc_b.dtype}: want two "
                           "sets of rows of one width and dtype")
    if len(desc_a) * len(desc_b) > MAX_MATCH_PAIRS:
        raise MessageError(f"{len(desc_a)} x {len(desc_b)} descriptors to match: at most {MAX_MATCH_PAIRS} pairs")


def main(argv: list[str] | None = None) -> None:
    serve(MatcherService, argv)
