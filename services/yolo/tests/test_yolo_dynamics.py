"""The dynamics table: the paper's defaults, selection by level, and clear errors for a bad table."""

from __future__ import annotations

import numpy as np
import pytest

from twohr.config import YoloConfig, load_config
from twohr.errors import ConfigError
from twohr.features import Detections
from twohr_services.yolo.dynamics import DynamicsTable, load_dynamics_table
from twohr_services.yolo.masks import DynamicMasker


def test_the_papers_table_is_the_default():
    table = load_dynamics_table()
    assert table.high == ["person"]
    assert table.medium == ["chair", "book"]
    assert table.low == ["dining table", "tv"]
    assert table.level_of("person") == "high"
    assert table.level_of("desk") == "low"  # the paper's word for COCO's dining table
    assert table.level_of("car") is None


def test_select_keeps_the_removed_levels():
    names = ["person", "chair", "tv", "car", "book"]
    detections = Detections(np.arange(20, dtype=np.float32).reshape(5, 4), np.full(5, 0.5, np.float32),
                            np.arange(5), names)
    table = load_dynamics_table()
    assert table.select(detections, ["high"]).names == ["person"]
    selected = table.select(detections, ["high", "medium"])
    assert selected.names == ["person", "chair", "book"]
    np.testing.assert_array_equal(selected.boxes, detections.boxes[[0, 1, 4]])
    assert table.select(detections, []).names == []
    assert table.levels_of(detections) == ["high", "medium", "low", None, "medium"]
    with pytest.raises(ConfigError, match="unknown dynamics level"):
        table.classes(["extreme"])


def test_an_edited_table_file(tmp_path):
    path = tmp_path / "table.yaml"
    path.write_text("high: [person, dog]\nmedium: [chair]\nlow: [desk, monitor]\n")
    table = load_dynamics_table(path)
    assert table.high == ["person", "dog"] and table.low == ["dining table", "tv"] and table.medium == ["chair"]


@pytest.mark.parametrize("text,match", [
    ("high: [person\n", "not valid YAML"),
    ("- person\n- chair\n", "expected a mapping of levels"),
    ("high: [person]\nextreme: [car]\n", "unknown dynamics level"),
    ("high: [person]\nmedium: [person]\n", "listed under both"),
    ("high: {person: 1}\n", "high"),
])
def test_malformed_tables_are_clear_errors(tmp_path, text, match):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=match) as info:
        load_dynamics_table(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value).split(": ", 1)[0]


def test_missing_table_and_unknown_level_in_config(tmp_path):
    with pytest.raises(ConfigError, match="dynamics table not found"):
        load_dynamics_table(tmp_path / "absent.yaml")
    with pytest.raises(ConfigError, match="yolo.remove_levels"):
        load_config(None, ["yolo.remove_levels=[high, extreme]"])


def test_table_naming_a_class_the_model_lacks(tmp_path):
    path = tmp_path / "typo.yaml"
    path.write_text("high: [persn]\n")
    with pytest.raises(ConfigError, match="persn"):
        DynamicMasker(YoloConfig(dynamics_table=str(path)))
    DynamicsTable(high=["person"]).check_names(["person", "chair"])


def test_a_table_is_named_the_papers_by_its_name_an_operators_from_its_folder(tmp_path, monkeypatch):
    from twohr_services.yolo.dynamics import TABLES_ENV

    paper = load_dynamics_table()
    assert load_dynamics_table("dynamics") == paper
    monkeypatch.setenv(TABLES_ENV, str(tmp_path))
    (tmp_path / "warehouse.yaml").write_text("high: [person, dog]\nlow: [chair]\n")
    table = load_dynamics_table("warehouse")
    assert table.high == ["person", "dog"] and table != paper
    with pytest.raises(ConfigError, match="'forklifts' is not installed"):
        load_dynamics_table("forklifts")
