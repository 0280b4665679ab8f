"""What a session does with a stored map: the modes, and every rule that depends on one, in one place.

The values are the strings of the HTTP API (``"map": {"name": "lab", "mode": "share"}``) and of the control
message's ``map_mode``; code compares :class:`MapMode` members or asks their properties, never a mode's string.
"""

from __future__ import annotations

from enum import Enum
from typing import Literal

from pydantic import BaseModel, Field

from .mapfile import NAME_PATTERN


class MapMode(str, Enum):
    NONE = ""  # the session has no map (the control message's value; never a request's)
    BUILD = "build"
    LOCALIZE = "localize"
    EXTEND = "extend"
    SHARE = "share"

    @property
    def reads_stored(self) -> bool:
        """The session starts in the stored map (a shared map only where one is stored already)."""
        return self in (MapMode.LOCALIZE, MapMode.EXTEND, MapMode.SHARE)

    @property
    def stored_optional(self) -> bool:
        """A missing stored map is no error: the first robot of a new shared map makes its frame."""
        return self is MapMode.SHARE

    @property
    def saves(self) -> bool:
        """The session's map is saved as the name's next version when it ends."""
        return self in (MapMode.BUILD, MapMode.EXTEND, MapMode.SHARE)

    @property
    def saved_by_tracker(self) -> bool:
        """The session's own tracker saves it; a shared map is saved by the map room once its last session ended."""
        return self in (MapMode.BUILD, MapMode.EXTEND)

    @property
    def shared(self) -> bool:
        """Many robots build the map at once: keyframes go to the map room, which merges each robot into the map."""
        return self is MapMode.SHARE

    @property
    def needs_rights(self) -> bool:
        """It changes an existing map: its robot must own the map or hold the operator's grant."""
        return self.saves

    @property
    def edge_allowed(self) -> bool:
        """A robot that tracks itself may use it (build and extend need the stack's tracker, which saves the map)."""
        return self in (MapMode.NONE, MapMode.LOCALIZE, MapMode.SHARE)

    @property
    def resumes_in_stored(self) -> bool:
        """A session moved to another tracker with no snapshot kept goes on in the stored map (a shared map's
        stored version no longer holds what the other robots added)."""
        return self in (MapMode.LOCALIZE, MapMode.EXTEND)


RequestedMode = Literal[MapMode.BUILD, MapMode.LOCALIZE, MapMode.EXTEND, MapMode.SHARE]


class MapRequest(BaseModel):
    """The map a session builds, localizes in, extends or shares (by name, in the map store)."""

    name: str = Field(pattern=NAME_PATTERN, description="the map's name, also the frame id of the session's poses")
    mode: RequestedMode = Field(
        MapMode.LOCALIZE, description="build: a new map, saved under the name when the session ends; localize: track "
        "in the map (not saved); extend: track in it, add keyframes, save as its next version; share: build it with "
        "every other robot sharing it at the same time (the map server merges each robot into the map's frame once "
        "its places are found there; saved as the next version when the last such session ends). Any robot may "
        "localize in any map; build, extend or share of an existing map needs its robot to own it (to have built "
        "it) or to hold the operator's grant (403 otherwise)")

    model_config = {"extra": "forbid"}
