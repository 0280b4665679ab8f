"""Where a robot's poses go in a session that shares a map (the map server's answer applied)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class SharedMapFrame:
    """Where a robot's poses go in a shared map: frame ``<map>/<robot>`` (its own) until the map server merges it,
    then the map's frame, through ``T`` (the robot's frame into the map's)."""

    map_name: str
    robot: str
    T: np.ndarray | None = None

    @property
    def frame_id(self) -> str:
        return self.map_name if self.T is not None else f"{self.map_name}/{self.robot}"

    def place(self, poses: np.ndarray) -> np.ndarray:
        """Camera-to-world poses (..., 4, 4) of the robot's frame, in :attr:`frame_id`."""
        return poses if self.T is None else self.T @ poses
