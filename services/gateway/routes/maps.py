"""``/maps``: the map store over HTTP (``--maps DIR``): list, download (the latest version or a kept one), upload
(checked through first), roll back, remove. Every robot's token reads; uploads, rollbacks and removals are the
operator's, and go into the audit trail (an upload's and a rollback's under the store's lock, as the map room's
saves).

The store is the folder the map room serves on the bus (``twohr/maps/<name>``, ``twohr_services.mapserver``), read
and written here through the store library (:mod:`twohr.mapstore`)."""

from __future__ import annotations

import logging
from typing import Annotated

from fastapi import APIRouter, Depends, HTTPException, Query, Request, status
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse

from twohr.mapfile import OPERATOR, MapFileError
from twohr.mapstore import MapEntry, MapMissingError, MapStore

from ..deps import Bus, Settings, Who, errors, require_token

log = logging.getLogger("twohr.gateway")

router = APIRouter(dependencies=[Depends(require_token)])


async def map_store(settings: Settings) -> MapStore:
    """The gateway's map store; 404 when it keeps none."""
    if settings.maps is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, "this gateway has no map store (twohr up --maps DIR)")
    return MapStore(settings.maps, settings.map_versions)


Store = Annotated[MapStore, Depends(map_store)]


@router.get("/maps", response_model=list[MapEntry], responses=errors(401, 404))
def list_maps(store: Store) -> list[MapEntry]:
    """The maps in the store (the latest version of each); an unreadable file is left out and logged."""
    good, bad = store.entries()
    for name, why in bad.items():
        log.warning("map %s is not readable: %s", name, why)
    return good


@router.get("/maps/{name}", responses={
    200: {"content": {"application/octet-stream": {}}, "description": "the map file"}, **errors(401, 404, 422)})
def download_map(name: str, store: Store, version: Annotated[int | None, Query(
        ge=1, le=2**31, description="a kept version's number (GET /maps lists them); default the latest")] = None,
                 ) -> FileResponse:
    """A map's file: its latest version, or a kept one."""
    try:
        path = store.latest_file(name) if version is None else store.version_path(name, version)
    except MapFileError as exc:
        raise HTTPException(status.HTTP_404_NOT_FOUND, str(exc)) from None
    return FileResponse(path, media_type="application/octet-stream", filename=f"{name}.v{version}.map"
                        if version is not None else f"{name}.map")


@router.post("/maps", status_code=201, response_model=MapEntry, responses=errors(401, 403, 404, 413, 422),
             openapi_extra={"requestBody": {"required": True, "content": {"application/octet-stream": {
                 "schema": {"type": "string", "format": "binary"}}}}})
async def upload_map(request: Request, store: Store, settings: Settings, bus: Bus, who: Who,
                     name: str | None = None) -> MapEntry:
    """Keep an uploaded map file (the body), checked through first, under its name (``name``, if given, must be
    the one in its header); a map already under that name is kept as an earlier version. The operator's only: a new
    map is the operator's; an existing one keeps its owners, with the operator among its contributors."""
    who.check_operator("uploading a map")
    chunks, size = [], 0
    async for chunk in request.stream():  # a chunked upload has no Content-Length for the middleware to check
        size += len(chunk)
        if size > settings.max_map_bytes:
            raise HTTPException(status.HTTP_413_CONTENT_TOO_LARGE, f"map over {settings.max_map_bytes} bytes")
        chunks.append(chunk)
    def audited(entry: MapEntry) -> None:
        bus.audit.record("map.upload", OPERATOR, map=entry.name, version=entry.version, detail=f"{size} bytes")

    try:  # checks and fsyncs: off the loop
        return await run_in_threadpool(store.save, b"".join(chunks), name, builder=OPERATOR, on_saved=audited)
    except MapFileError as exc:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, str(exc)[:2000]) from None


@router.post("/maps/{name}/rollback", response_model=MapEntry, responses=errors(401, 403, 404, 409, 422))
def rollback_map(name: str, store: Store, bus: Bus, who: Who, version: Annotated[int, Query(
        ge=1, le=2**31, description="the kept version to make the latest again (GET /maps lists them)")]) -> MapEntry:
    """Make an earlier version of a map the latest again, byte for byte, as a new version (the versions after it
    are kept, until the store's limit prunes them). 404 for a version not kept, 409 for the latest itself or a
    version no longer readable. The operator's only."""
    who.check_operator("rolling a map back")
    try:
        store.path(name)
    except MapFileError as exc:  # not a name a map can have
        raise HTTPException(status.HTTP_404_NOT_FOUND, str(exc)) from None
    def audited(entry: MapEntry) -> None:
        bus.audit.record("map.rollback", OPERATOR, map=name, version=entry.version,
                         detail=f"version {entry.version} is version {version}'s bytes")

    try:
        return store.rollback(name, version, on_saved=audited)
    except MapMissingError as exc:
        raise HTTPException(status.HTTP_404_NOT_FOUND, str(exc)) from None
    except MapFileError as exc:  # the latest already, or a kept file no longer readable
        raise HTTPException(status.HTTP_409_CONFLICT, str(exc)[:2000]) from None


@router.delete("/maps/{name}", status_code=204, responses=errors(401, 403, 404))
def delete_map(name: str, store: Store, bus: Bus, who: Who) -> None:
    """Remove a map and its earlier versions. The operator's only."""
    who.check_operator("deleting a map")
    try:
        removed = store.delete(name)
    except MapFileError as exc:
        raise HTTPException(status.HTTP_404_NOT_FOUND, str(exc)) from None
    if not removed:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"no map named {name!r}")
    bus.audit.record("map.delete", OPERATOR, map=name)
