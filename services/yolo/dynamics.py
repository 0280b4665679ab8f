"""The paper's dynamics table: object classes by how likely they are to move (high, medium, low).

The table is a YAML file users can edit (``dynamics.yaml`` beside this module is the paper's):
a mapping from level to a list of class names. :meth:`DynamicsTable.select` keeps the
detections whose class belongs to the levels that should be removed.
"""

from __future__ import annotations

import os
from importlib import resources
from pathlib import Path
from typing import Literal, get_args

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from twohr.config import is_table_name
from twohr.errors import ConfigError, validation_problems
from twohr.features import Detections

Level = Literal["high", "medium", "low"]
LEVELS: tuple[str, ...] = get_args(Level)

#: Words the paper (or a user) may use for a COCO class.
CLASS_ALIASES = {"desk": "dining table", "table": "dining table", "monitor": "tv", "tvmonitor": "tv",
                 "people": "person", "human": "person"}


class DynamicsTable(BaseModel):
    """Class names per dynamics level; a class belongs to at most one level."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    high: list[str] = Field(default_factory=list, description="classes that move on their own (person)")
    medium: list[str] = Field(default_factory=list, description="classes people move often (chair, book)")
    low: list[str] = Field(default_factory=list, description="classes that rarely move (desk, tv)")

    @field_validator("high", "medium", "low", mode="before")
    @classmethod
    def _canonical_names(cls, value: object) -> object:
        if value is None:
            return []
        if isinstance(value, str):
            value = [value]
        if isinstance(value, list):
            return [CLASS_ALIASES.get(str(v).strip().lower(), str(v).strip().lower()) for v in value]
        return value

    @model_validator(mode="after")
    def _one_level_per_class(self) -> DynamicsTable:
        seen: dict[str, str] = {}
        for level in LEVELS:
            for name in getattr(self, level):
                if name in seen:
                    raise ValueError(f"class {name!r} is listed under both {seen[name]!r} and {level!r}")
                seen[name] = level
        return self

    def level_of(self, name: str) -> str | None:
        """The dynamics level of a class name, or None for a static class."""
        name = CLASS_ALIASES.get(name.lower(), name.lower())
        return next((level for level in LEVELS if name in getattr(self, level)), None)

    def classes(self, levels: list[str] | tuple[str, ...]) -> set[str]:
        """All class names of the given levels."""
        unknown = [lv for lv in levels if lv not in LEVELS]
        if unknown:
            raise ConfigError(f"unknown dynamics level(s) {unknown}; choose from {list(LEVELS)}")
        return {name for level in levels for name in getattr(self, level)}

    def check_names(self, known: list[str], model: str = "the model") -> None:
        """Raise :class:`ConfigError` if the table names a class that the detector does not know."""
        unknown = sorted(set().union(*(getattr(self, lv) for lv in LEVELS)) - set(known))
        if unknown:
            raise ConfigError(f"dynamics table names class(es) {unknown} that {model} does not detect; "
                              f"known classes: {', '.join(known)}")

    def levels_of(self, detections: Detections) -> list[str | None]:
        """The level of each detection (None = static)."""
        return [self.level_of(n) for n in detections.names]

    def select(self, detections: Detections, levels: list[str] | tuple[str, ...]) -> Detections:
        """The detections whose class is in one of ``levels``: the objects to mask."""
        wanted = self.classes(levels)
        keep = np.array([n in wanted for n in detections.names], bool)
        if len(detections) == 0 or keep.all():
            return detections
        return Detections(detections.boxes[keep], detections.scores[keep], detections.class_ids[keep],
                          [n for n, k in zip(detections.names, keep, strict=True) if k])


#: where the operator installs dynamics tables a session may name (``<name>.yaml``)
TABLES_ENV = "TWOHR_DYNAMICS_TABLES"
#: the name of the table the stack ships (the paper's)
PAPER_TABLE = "dynamics"


def load_dynamics_table(path: str | Path | None = None) -> DynamicsTable:
    """The paper's table (``dynamics.yaml`` beside this module) when ``path`` is None or its name; a table's name
    (:func:`twohr.config.is_table_name`): ``<name>.yaml`` in ``$TWOHR_DYNAMICS_TABLES``; else a YAML file's path
    (in process only: the gateway refuses one).

    Raises :class:`ConfigError` with the file name for a missing file, invalid YAML, an unknown
    level or a class listed under two levels."""
    if isinstance(path, str) and is_table_name(path):
        if path == PAPER_TABLE:
            path = None
        else:
            folder = os.environ.get(TABLES_ENV)
            if not folder or not (Path(folder) / f"{path}.yaml").is_file():
                raise ConfigError(f"dynamics table {path!r} is not installed: the stack ships {PAPER_TABLE!r}; the "
                                  f"operator adds <name>.yaml to ${TABLES_ENV}")
            path = Path(folder) / f"{path}.yaml"
    if path is None:
        text = resources.files(__package__).joinpath("dynamics.yaml").read_text()
        where = "the built-in dynamics table"
    else:
        path = Path(path)
        if not path.is_file():
            raise ConfigError(f"dynamics table not found: {path}")
        text = path.read_text()
        where = str(path)
    try:
        data = yaml.safe_load(text) or {}
    except yaml.YAMLError as exc:
        raise ConfigError(f"{where}: not valid YAML: {exc}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected a mapping of levels ({', '.join(LEVELS)}) to lists of class names")
    unknown = [str(k) for k in data if k not in LEVELS]
    if unknown:
        raise ConfigError(f"{where}: unknown dynamics level(s) {unknown}; the levels are {', '.join(LEVELS)}")
    try:
        return DynamicsTable.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(f"{where}: {validation_problems(exc, empty_location='table')}") from None
