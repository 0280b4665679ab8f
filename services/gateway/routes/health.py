"""``GET /healthz``: the gateway's liveness and every pipeline service's counters."""

from __future__ import annotations

from fastapi import APIRouter

from twohr.bus import query_health
from twohr.keys import PIPELINE_SERVICES

from ..deps import Bus

router = APIRouter()


@router.get("/healthz")
def healthz(bus: Bus) -> dict:
    """Gateway liveness plus each service's counters (null when a service does not answer)."""
    zsession = bus.session
    services = {name: query_health(zsession, name, timeout=0.5) for name in PIPELINE_SERVICES} if zsession else {}
    return {"status": "ok", "services": services}
