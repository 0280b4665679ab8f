"""The map modes' rules live in twohr.mapmodes alone: no product code compares a mode's string, and the strings on the
wire and over HTTP stay what they were."""

from __future__ import annotations

import ast
import json
from pathlib import Path

import pytest
from pydantic import ValidationError

from twohr.mapmodes import MapMode, MapRequest
from twohr.messages import ControlMsg, decode, encode

ROOT = Path(__file__).resolve().parents[1]
PRODUCT = ("shared", "services", "app")
MODE_STRINGS = {mode.value for mode in MapMode if mode is not MapMode.NONE}


def _mode_literals(node: ast.AST) -> list[str]:
    """The map-mode strings a comparison's operand spells out (itself, or inside a tuple, list or set)."""
    items = node.elts if isinstance(node, ast.Tuple | ast.List | ast.Set) else [node]
    return [item.value for item in items if isinstance(item, ast.Constant) and item.value in MODE_STRINGS]


def mode_string_comparisons(source: str) -> list[tuple[int, str]]:
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Compare):
            for operand in (node.left, *node.comparators):
                found += [(node.lineno, literal) for literal in _mode_literals(operand)]
    return found


def test_the_scan_finds_a_mode_compared_as_a_string():
    assert mode_string_comparisons('if control.map_mode == "share": pass') == [(1, "share")]
    assert mode_string_comparisons('ok = mode not in ("build", "extend")') == [(1, "build"), (1, "extend")]
    assert mode_string_comparisons('if control.map_mode.shared: pass') == []


def test_no_product_code_compares_a_map_mode_string():
    offenders = []
    for room in PRODUCT:
        for path in sorted((ROOT / room).rglob("*.py")):
            if "tests" in path.relative_to(ROOT).parts or path == ROOT / "shared" / "mapmodes.py":
                continue
            offenders += [f"{path.relative_to(ROOT)}:{line} compares {literal!r}"
                          for line, literal in mode_string_comparisons(path.read_text())]
    assert offenders == [], "map modes are compared in twohr.mapmodes only:\n" + "\n".join(offenders)


@pytest.mark.parametrize("mode, fetches, saves, by_tracker, edge", [
    ("build", False, True, True, False),
    ("localize", True, False, False, True),
    ("extend", True, True, True, False),
    ("share", True, True, False, True),
])
def test_each_mode_s_rules(mode, fetches, saves, by_tracker, edge):
    rules = MapMode(mode)
    assert (rules.reads_stored, rules.saves, rules.saved_by_tracker, rules.edge_allowed) == (
        fetches, saves, by_tracker, edge)
    assert rules.needs_rights == saves
    assert rules.shared == rules.stored_optional == (mode == "share")


def test_no_map_is_a_mode_that_does_nothing():
    none = MapMode.NONE
    assert not (none.reads_stored or none.saves or none.shared or none.needs_rights or none.resumes_in_stored)


def test_the_strings_over_http_and_on_the_wire_are_unchanged():
    request = MapRequest.model_validate({"name": "lab", "mode": "share"})
    assert request.mode is MapMode.SHARE and json.loads(request.model_dump_json()) == {"name": "lab", "mode": "share"}
    with pytest.raises(ValidationError):
        MapRequest.model_validate({"name": "lab", "mode": ""})  # "no map" is the control message's alone
    control = ControlMsg(session_id="s1", robot_id="a", frame_index=-1, stamp=0.0, command="start", map_name="lab",
                         map_mode="extend", started_by="a")
    decoded, _ = decode(encode(control), ControlMsg)
    assert decoded.map_mode is MapMode.EXTEND and decoded.map_request == MapRequest(name="lab", mode="extend")
    assert decoded.started_by == "a"
    assert json.loads(control.model_dump_json())["map_mode"] == "extend"
    plain, _ = decode(encode(ControlMsg(session_id="s1", robot_id="a", frame_index=-1, stamp=0.0, command="stop")),
                      ControlMsg)
    assert plain.map_mode is MapMode.NONE and plain.map_request is None
