"""``GET /healthz``: whether the stack is up, to anyone; to the operator, also the stack's load against its capacity
and every pipeline service's counters (each replica's under ``replicas``)."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Depends, HTTPException, Request
from pydantic import BaseModel, Field

from twohr.bus import query_health
from twohr.keys import PIPELINE_SERVICES

from ..admission import admitted_load
from ..deps import Bus, Caller, Settings, Table, Tokens, require_token, token_check

router = APIRouter()


class StackUp(BaseModel):
    """``/healthz`` without the operator's token: whether the stack is up, nothing of its robots or hosts."""

    status: Literal["up", "down"] = Field(description="up: the gateway answers and every pipeline service has a "
                                          "replica alive")


async def _caller(request: Request, check: Annotated[Tokens, Depends(token_check)]) -> Caller | None:
    """Who asks, or None for a request without a token the gateway knows: liveness answers everyone."""
    try:
        return await require_token(request, check)
    except HTTPException:
        return None


@router.get("/healthz", response_model=None)
def healthz(bus: Bus, table: Table, settings: Settings,
            caller: Annotated[Caller | None, Depends(_caller)]) -> StackUp | dict:
    """Whether the stack is up (``StackUp``) to anyone; the operator's token (or a gateway with no token, on loopback)
    also sees: ``degraded`` with the reason while a live session is (its tracker drops frames or its keyframe jobs
    come back late: more robots than the CPU serves) or a pipeline service has no replica alive; the admitted load
    in robots against the capacity; every tracker with its host, process id and robots (``trackers``); each
    service's counters, its replicas and their hosts (null when no replica answers). A robot's token sees what
    anyone does: other robots' ids and the replicas' hosts are the operator's."""
    missing = bus.missing_services()  # no liveliness token up: POST /sessions answers 503 until they are back
    if caller is None or caller.robot is not None:  # and no bus query for a caller without the token
        return StackUp(status="down" if missing else "up")
    zsession = bus.session
    services = {name: query_health(zsession, name, timeout=0.5) for name in PIPELINE_SERVICES} if zsession else {}
    degraded = [f"{s.request.robot_id}: {s.health_detail}" for s in table.active() if s.health == "degraded"]
    reasons = degraded + ([f"services not running: {', '.join(missing)}"] if missing else [])
    return {"status": "degraded" if reasons else "ok", "reason": "; ".join(reasons), "missing_services": missing,
            "robots": {"admitted": admitted_load(table), "capacity": settings.max_robots},
            "trackers": trackers(services.get("tracker")), "services": services}


def trackers(health: dict | None) -> list[dict]:
    """Every tracker that answered: its replica, host, process id and the robots whose sessions it serves."""
    answers = (health or {}).get("replicas", [])
    return [{key: answer.get(key) for key in ("replica", "host", "pid", "robots")} for answer in answers]
