"""``GET /healthz``: the gateway's liveness, the stack's load against its capacity, and every pipeline service's
counters (each replica's under ``replicas``)."""

from __future__ import annotations

from fastapi import APIRouter

from twohr.bus import query_health
from twohr.keys import PIPELINE_SERVICES

from ..admission import admitted_load
from ..deps import Bus, Settings, Table

router = APIRouter()


@router.get("/healthz")
def healthz(bus: Bus, table: Table, settings: Settings) -> dict:
    """Gateway liveness; ``degraded`` with the reason while a live session is (its tracker drops frames or its
    keyframe jobs come back late: more robots than the CPU serves) or a pipeline service has no replica alive; the
    admitted load in robots against the capacity; each service's counters (null when no replica answers)."""
    zsession = bus.session
    services = {name: query_health(zsession, name, timeout=0.5) for name in PIPELINE_SERVICES} if zsession else {}
    degraded = [f"{s.request.robot_id}: {s.health_detail}" for s in table.active() if s.health == "degraded"]
    missing = bus.missing_services()  # no liveliness token up: POST /sessions answers 503 until they are back
    reasons = degraded + ([f"services not running: {', '.join(missing)}"] if missing else [])
    return {"status": "degraded" if reasons else "ok", "reason": "; ".join(reasons), "missing_services": missing,
            "robots": {"admitted": admitted_load(table), "capacity": settings.max_robots}, "services": services}
