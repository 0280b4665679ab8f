"""``/maps``: the map store over HTTP (``--maps DIR``): list, download, upload (checked through first), remove.

The store is the same folder the gateway serves on the bus (``twohr/maps/<name>``, see ``..bus``)."""

from __future__ import annotations

import logging
from typing import Annotated

from fastapi import APIRouter, Depends, HTTPException, Request, status
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse

from twohr.mapfile import MapEntry, MapFileError, MapStore

from ..deps import Settings, Who, errors, require_token

log = logging.getLogger("twohr.gateway")

router = APIRouter(dependencies=[Depends(require_token)])


async def map_store(settings: Settings) -> MapStore:
    """The gateway's map store; 404 when it keeps none."""
    if settings.maps is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, "this gateway has no map store (twohr up --maps DIR)")
    return MapStore(settings.maps)


Store = Annotated[MapStore, Depends(map_store)]


@router.get("/maps", response_model=list[MapEntry], responses=errors(401, 404))
def list_maps(store: Store) -> list[MapEntry]:
    """The maps in the store (the latest version of each); an unreadable file is left out and logged."""
    good, bad = store.entries()
    for name, why in bad.items():
        log.warning("map %s is not readable: %s", name, why)
    return good


@router.get("/maps/{name}", responses={
    200: {"content": {"application/octet-stream": {}}, "description": "the map file"}, **errors(401, 404)})
def download_map(name: str, store: Store) -> FileResponse:
    """A map's file (its latest version)."""
    try:
        path = store.path(name)
    except MapFileError as exc:
        raise HTTPException(status.HTTP_404_NOT_FOUND, str(exc)) from None
    if not path.is_file():
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"no map named {name!r}")
    return FileResponse(path, media_type="application/octet-stream", filename=path.name)


@router.post("/maps", status_code=201, response_model=MapEntry, responses=errors(401, 403, 404, 413, 422),
             openapi_extra={"requestBody": {"required": True, "content": {"application/octet-stream": {
                 "schema": {"type": "string", "format": "binary"}}}}})
async def upload_map(request: Request, store: Store, settings: Settings, who: Who,
                     name: str | None = None) -> MapEntry:
    """Keep an uploaded map file (the body), checked through first, under its name (``name``, if given, must be
    the one in its header); a map already under that name is kept as an earlier version. The operator's only."""
    who.check_operator("uploading a map")
    chunks, size = [], 0
    async for chunk in request.stream():  # a chunked upload has no Content-Length for the middleware to check
        size += len(chunk)
        if size > settings.max_map_bytes:
            raise HTTPException(status.HTTP_413_CONTENT_TOO_LARGE, f"map over {settings.max_map_bytes} bytes")
        chunks.append(chunk)
    try:
        return await run_in_threadpool(store.save, b"".join(chunks), name)  # checks and fsyncs: off the loop
    except MapFileError as exc:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, str(exc)[:2000]) from None


@router.delete("/maps/{name}", status_code=204, responses=errors(401, 403, 404))
def delete_map(name: str, store: Store, who: Who) -> None:
    """Remove a map and its earlier versions. The operator's only."""
    who.check_operator("deleting a map")
    try:
        removed = store.delete(name)
    except MapFileError as exc:
        raise HTTPException(status.HTTP_404_NOT_FOUND, str(exc)) from None
    if not removed:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"no map named {name!r}")
