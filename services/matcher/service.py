"""The matcher service: answers match queries on ``twohr/<robot>/rpc/match`` and publishes each result
on ``twohr/<robot>/matches``.

The tracker asks it to match the current frame's descriptors against its local map, so the
learned matcher runs in its own process (and can be moved to a GPU box) while the tracker
keeps the map.
"""

from __future__ import annotations

import time

from twohr import keys
from twohr.config import MatcherConfig
from twohr.messages import MatchesMsg, MatchRequestMsg, decode, encode
from twohr.service import Service, serve

from .core import build_matcher


class MatcherService(Service):
    """Siamese (or baseline) matching as a query/reply service, with each session's matcher config."""

    name = "matcher"
    follows_sessions = True

    def __init__(self, bus=None) -> None:
        super().__init__(bus, queue_size=16, policy="backpressure")
        self.matchers: dict[str, object] = {}
        self.queryable = None

    def on_start(self) -> None:
        self.queryable = self.session.declare_queryable(keys.all_robots(keys.MATCH_QUERY), self._on_query)

    def matcher_for(self, conf: MatcherConfig):
        key = conf.model_dump_json()
        if key not in self.matchers:
            self.matchers[key] = build_matcher(conf)
        return self.matchers[key]

    def handle(self, key: str, query) -> None:
        payload = query.payload.to_bytes() if query.payload is not None else b""
        try:
            request, arrays = decode(payload, MatchRequestMsg)
        except Exception:
            query.reply_err(b"malformed match request")
            raise
        match = self.matcher_for(self.config_for(request.session_id).matcher)
        t0 = time.perf_counter()
        matches = match(arrays["desc_a"], arrays["desc_b"])
        reply = MatchesMsg(session_id=request.session_id, robot_id=request.robot_id, frame_index=request.frame_index,
                           stamp=request.stamp, reference=request.reference,
                           elapsed_ms=(time.perf_counter() - t0) * 1000)
        data = encode(reply, {"idx_a": matches.idx_a.astype("int64"), "idx_b": matches.idx_b.astype("int64"),
                              "scores": matches.scores.astype("float32")})
        query.reply(query.key_expr, data)
        self.publish(keys.key(request.robot_id, "matches"), data)


def main(argv: list[str] | None = None) -> None:
    serve(MatcherService, argv)
