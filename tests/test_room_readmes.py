"""Each room's README lists the room's modules, and the list cannot drift from the folder.

A room's README (``services/<room>/README.md``) holds one module table: its header's first cell is ``file`` or
``module``, and each row's first cell is one file name in backticks. The rows without a folder must be exactly the
room's top-level modules (every ``*.py`` directly in the room's folder but ``__init__.py``; ``__main__.py`` is one).
A file of another room, or of a sub-folder, may be named in the table with its folder (``shared/places.py``,
``routes/maps.py``): it is not counted as the room's, but it must exist."""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SERVICES = REPO / "services"
#: the first header cell of a room's module table
TABLE_HEADS = ("file", "module")
#: a row's first cell: one file name in backticks, with or without its folder
NAME_CELL = re.compile(r"`([\w./-]+\.py)`")


def service_rooms() -> list[str]:
    return sorted(p.name for p in SERVICES.iterdir() if (p / "__init__.py").is_file())


def room_modules(room_folder: Path) -> set[str]:
    return {p.name for p in room_folder.glob("*.py") if p.name != "__init__.py"}


def _cells(line: str) -> list[str]:
    return [cell.strip() for cell in re.split(r"(?<!\\)\|", line.strip().strip("|"))]


def module_table(readme: str) -> list[str] | None:
    """The first cells of the module table's rows (None when the README has no module table)."""
    lines = readme.splitlines()
    for i, line in enumerate(lines[:-1]):
        if not (line.lstrip().startswith("|") and re.fullmatch(r"\|?[\s:|-]+\|?", lines[i + 1].strip())):
            continue
        if _cells(line)[0].lower() not in TABLE_HEADS:
            continue
        rows = []
        for row in lines[i + 2:]:
            if not row.lstrip().startswith("|"):
                break
            rows.append(_cells(row)[0])
        return rows
    return None


def table_problems(room: str, readme: str, modules: set[str], room_folder: Path) -> list[str]:
    """What is wrong with ``room``'s module table: missing modules, rows for files that are not the room's, rows
    that name no single file, other folders' files that do not exist. Empty when the table is right."""
    where = f"services/{room}/README.md"
    rows = module_table(readme)
    if rows is None:
        return [f"{where}: no module table (a table whose first column is headed "
                f"{' or '.join(repr(h) for h in TABLE_HEADS)})"]
    problems, named = [], []
    for cell in rows:
        found = NAME_CELL.fullmatch(cell)
        if not found:
            problems.append(f"{where}: the row {cell!r} names no single file in backticks (e.g. `service.py`)")
            continue
        name = found.group(1)
        if "/" not in name:
            named.append(name)
        elif not ((REPO / name).is_file() or (room_folder / name).is_file()):
            problems.append(f"{where}: the row `{name}` names a file that does not exist")
    doubled = sorted({name for name in named if named.count(name) > 1})
    missing, extra = sorted(modules - set(named)), sorted(set(named) - modules)
    if missing:
        problems.append(f"{where}: room {room} has modules with no row: {missing}")
    if extra:
        problems.append(f"{where}: room {room} has rows for files that are not its modules: {extra} "
                        "(a file of another room or folder is named with its folder, e.g. `shared/places.py`)")
    if doubled:
        problems.append(f"{where}: room {room} has more than one row for {doubled}")
    return problems


MADE_UP_README = """# room — a made-up one

| direction | key | what |
|---|---|---|
| subscribes | `twohr/*/frames` | not the module table: its first column is not `file` |

| file | what |
|---|---|
| `core.py` | the core |
| `core.py` | the core again |
| `places.py` | now shared: drawn in the wrong room |
| `shared/places.py` | named with its folder: not the room's |
| `shared/gone.py` | named with its folder, but there is no such file |
| `map.py`, `mapfiles.py` | two files in one row |
| `__main__.py` | the entry point |

Text after the table.
"""


def test_the_readme_check_can_fail(tmp_path):
    """A made-up README: a module missing, a file of another room drawn as the room's, a doubled row, a row of two
    files, a file named with its folder that does not exist; and a README with no module table at all."""
    modules = {"core.py", "service.py", "__main__.py"}
    assert module_table(MADE_UP_README) == ["`core.py`", "`core.py`", "`places.py`", "`shared/places.py`",
                                            "`shared/gone.py`", "`map.py`, `mapfiles.py`", "`__main__.py`"]
    problems = table_problems("made_up", MADE_UP_README, modules, tmp_path)
    assert problems == [
        "services/made_up/README.md: the row `shared/gone.py` names a file that does not exist",
        "services/made_up/README.md: the row '`map.py`, `mapfiles.py`' names no single file in backticks "
        "(e.g. `service.py`)",
        "services/made_up/README.md: room made_up has modules with no row: ['service.py']",
        "services/made_up/README.md: room made_up has rows for files that are not its modules: ['places.py'] "
        "(a file of another room or folder is named with its folder, e.g. `shared/places.py`)",
        "services/made_up/README.md: room made_up has more than one row for ['core.py']",
    ]
    right = ("| module | what |\n|:--|--:|\n| `core.py` | the core |\n| `service.py` | the shell |\n"
             "| `shared/places.py` | another room's |\n| `__main__.py` | the entry point |\n")
    assert table_problems("made_up", right, modules, tmp_path) == []
    assert table_problems("made_up", "# room\n\nNo table here.\n", modules, tmp_path) == [
        "services/made_up/README.md: no module table (a table whose first column is headed 'file' or 'module')"]
    (tmp_path / "routes").mkdir()
    (tmp_path / "routes" / "maps.py").write_text("")
    assert table_problems("made_up", right + "| `routes/maps.py` | a sub-folder's |\n", modules, tmp_path) == []


def test_every_room_readme_lists_exactly_the_rooms_modules():
    rooms = service_rooms()
    assert {"detector", "yolo", "matcher", "tracker", "source", "recorder", "gateway", "mapserver", "ros2"} <= set(
        rooms)
    problems = []
    for room in rooms:
        folder = SERVICES / room
        readme = folder / "README.md"
        if not readme.is_file():
            problems.append(f"services/{room}: no README.md")
            continue
        problems += table_problems(room, readme.read_text(), room_modules(folder), folder)
    assert not problems, "\n".join(problems)
