"""``/audit``: the audit trail (who started, stopped or failed a session, who saved, uploaded, rolled back or
deleted a map, who was granted a map, added or revoked, with the time), the operator's only."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Query
from fastapi.concurrency import run_in_threadpool

from ..audit import AuditEvent
from ..deps import Bus, Who, errors, require_token

router = APIRouter(dependencies=[Depends(require_token)])


@router.get("/audit", response_model=list[AuditEvent], responses=errors(401, 403, 422))
async def audit_trail(bus: Bus, who: Who,
                      limit: Annotated[int, Query(ge=1, le=100_000, description="the newest this many")] = 1000,
                      since: Annotated[float | None, Query(ge=0, le=1e11, description="from this Unix time on")]
                      = None) -> list[AuditEvent]:
    """The audit trail, oldest first (the newest ``limit`` events). The operator's token only: 403 for a robot's."""
    who.check_operator("reading the audit trail")
    return await run_in_threadpool(bus.audit.read, limit, since)
