"""The README is the front door and the rest is the documentation site (mkdocs.yml, docs/): the README stays short,
keeps the licences and links only what exists; the site lists every page; its HTTP API and bus key pages are made
from the code (docs/hooks.py), not written by hand. ``make docs`` (part of ``make test``) builds it strictly."""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs"
#: the pages docs/hooks.py makes at build time
GENERATED = {"http-api.md", "bus-keys.md"}


def load_hooks():
    spec = importlib.util.spec_from_file_location("twohr_docs_hooks", DOCS / "hooks.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def nav_pages(nav) -> list[str]:
    pages = []
    for entry in nav:
        for value in entry.values() if isinstance(entry, dict) else [entry]:
            pages += nav_pages(value) if isinstance(value, list) else [value]
    return pages


def test_the_readme_is_a_short_front_door_that_keeps_the_licences():
    readme = (REPO / "README.md").read_text()
    assert len(readme.splitlines()) <= 200
    for text in ("make demo", "make test", "twohr run", "twohr up", "POST /sessions", "twohr/*/pose",
                 "CC BY-NC-SA 3.0", "non-commercial", "AGPL-3.0", "](docs/licences.md)"):
        assert text in readme, text
    links = re.findall(r"\]\(([^)#]+)", readme)
    assert "docs/img/demo-trajectory.png" in links
    assert [link for link in links if "://" not in link and not (REPO / link).is_file()] == []


def test_the_site_lists_every_page_and_builds_outside_the_source_tree():
    config = yaml.safe_load((REPO / "mkdocs.yml").read_text())
    assert config["site_dir"].startswith("runs/") and config["strict"] is True
    assert config["validation"]["nav"]["omitted_files"] == "warn"
    pages = nav_pages(config["nav"])
    written = {p.name for p in DOCS.glob("*.md")}
    assert sorted(pages) == sorted(written | GENERATED)
    assert not written & GENERATED  # made at build time only


def test_the_api_and_key_pages_are_made_from_the_code():
    from twohr import keys

    hooks = load_hooks()
    schema = hooks.openapi_schema()
    api = hooks.api_page(schema)
    for path, operations in schema["paths"].items():
        for method in operations:
            assert f"| {method.upper()} | `{path}` |" in api
    assert "`SessionRequest` (application/json)" in api
    table = hooks.keys_page()
    assert "| `twohr/<robot>/pose` | `PoseMsg`" in table and "put: tracker |" in table
    assert "| `twohr/<robot>/rpc/detect/<replica>` |" in table and "answer: detector | ask: tracker |" in table
    assert all(keys.CARRIES[name].split(":")[0] in table for name in keys.CARRIES)


# --- the architecture page against the code -------------------------------------------------------------------------

SERVICES = REPO / "services"
ARCHITECTURE = DOCS / "architecture.md"


def section(page: str, heading: str) -> str:
    """The text under ``heading`` (a whole heading line, ``## ...`` or ``### ...``) up to the next heading of any
    level."""
    lines = page.splitlines()
    start = lines.index(heading) + 1
    end = next((i for i in range(start, len(lines)) if re.match(r"#{1,6} ", lines[i])), len(lines))
    return "\n".join(lines[start:end])


def table_rows(text: str, first_header: str) -> list[list[str]]:
    """The rows (their cells) of the first Markdown table in ``text`` whose first header cell is ``first_header``."""
    lines = text.splitlines()
    for i, line in enumerate(lines):
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if line.startswith("|") and cells[0] == first_header:
            rows = []
            for row in lines[i + 2:]:
                if not row.startswith("|"):
                    break
                rows.append([c.strip() for c in row.strip().strip("|").split("|")])
            return rows
    raise AssertionError(f"no table headed {first_header!r}")


def shared_table_problems(text: str, shared_modules: set[str]) -> list[str]:
    """The common library's table against ``shared/``: one row per module, named ``shared/<module>.py``."""
    named = {m for row in table_rows(text, "module") for m in re.findall(r"`shared/(\w+)\.py`", row[0])}
    missing, extra = sorted(shared_modules - named), sorted(named - shared_modules)
    return [f"shared/ modules the page does not list: {missing}"] * bool(missing) + [
        f"listed as shared/ modules but not there: {extra}"] * bool(extra)


def rooms_table_problems(text: str, services: Path) -> list[str]:
    """Every file the rooms table draws in a room is in that room (a ``name.py`` or a ``folder/``), and every room is
    drawn."""
    problems, drawn = [], set()
    for row in table_rows(text, "room"):
        room = row[0].strip("`")
        drawn.add(room)
        for name in re.findall(r"`([\w./]+)`", row[1]):
            if not (services.parent / room / name).exists():
                problems.append(f"{name} is drawn in {room}, which has no such file")
    rooms = {f"services/{p.name}" for p in services.iterdir() if (p / "__init__.py").is_file()}
    return problems + [f"rooms the table does not draw: {sorted(rooms - drawn)}"] * bool(rooms - drawn)


def drawn_rows(drawing: str) -> dict[str, int]:
    """module -> its row in a text drawing of a room, from the top: each line that does not start with a space draws
    the ``name.py`` files it names (continuation lines are indented)."""
    rows: dict[str, int] = {}
    for row, line in enumerate(line for line in drawing.splitlines() if line and not line[0].isspace()):
        for name in re.findall(r"\b(\w+)\.py\b", line):
            rows[name] = row
    return rows


def room_imports(folder: Path) -> dict[str, set[str]]:
    """module -> the modules of the same room it imports (relative or absolute, ``if TYPE_CHECKING:`` ones too)."""
    import ast

    package = f"twohr_services.{folder.name}"
    modules = {p.stem for p in folder.glob("*.py") if p.stem != "__init__"}
    found: dict[str, set[str]] = {}
    for name in modules:
        imported = set()
        for node in ast.walk(ast.parse((folder / f"{name}.py").read_text())):
            if isinstance(node, ast.ImportFrom) and node.level == 1:
                imported |= {node.module.split(".")[0]} if node.module else {a.name for a in node.names}
            elif isinstance(node, ast.ImportFrom) and (node.module or "").startswith(package + "."):
                imported.add(node.module.split(".")[2])
            elif isinstance(node, ast.Import):
                imported |= {a.name.split(".")[2] for a in node.names if a.name.startswith(package + ".")}
        found[name] = imported & modules
    return found


def drawing_problems(rows: dict[str, int], imports: dict[str, set[str]]) -> list[str]:
    """What a room's drawing gets wrong: modules it leaves out or that are not there, and any module drawn above one
    it imports (a module imports only modules drawn on its row or below)."""
    problems = [f"not drawn: {sorted(set(imports) - set(rows))}"] * bool(set(imports) - set(rows))
    problems += [f"drawn but not in the room: {sorted(set(rows) - set(imports))}"] * bool(set(rows) - set(imports))
    problems += [f"{m}.py is drawn below {i}.py, which it imports" for m in sorted(set(rows) & set(imports))
                 for i in sorted(imports[m]) if i in rows and rows[i] < rows[m]]
    return problems


def one_user_exceptions(text: str) -> set[str]:
    """The shared modules the page says stay shared with one user: those named in the bullet that names
    ``SHARED_WITH_ONE_USER``."""
    bullet = next(b for b in re.split(r"\n\s*\n|\n(?=- )", text) if "SHARED_WITH_ONE_USER" in b)
    return set(re.findall(r"`shared/(\w+)\.py`", bullet))


def test_the_architecture_checks_can_fail(tmp_path):
    """Made-up pages and rooms: a shared module left out and one that is gone, a file drawn in the wrong room, a room
    left out, a module drawn above one it imports, an exception that is no longer one."""
    shared = "| module | what |\n|---|---|\n| `shared/keys.py` | keys |\n| `shared/gone.py` | gone |\n"
    assert shared_table_problems(shared, {"keys", "ids"}) == ["shared/ modules the page does not list: ['ids']",
                                                              "listed as shared/ modules but not there: ['gone']"]
    assert shared_table_problems(shared.replace("gone", "ids"), {"keys", "ids"}) == []
    services = tmp_path / "services"
    for room, files in {"tracker": ["map.py"], "mapserver": ["core.py"]}.items():
        (services / room).mkdir(parents=True)
        for name in ["__init__.py", *files]:
            (services / room / name).write_text("")
    rooms = "| room | files | what |\n|---|---|---|\n| `services/tracker` | `map.py`, `places.py` | the map |\n"
    assert rooms_table_problems(rooms, services) == ["places.py is drawn in services/tracker, which has no such file",
                                                     "rooms the table does not draw: ['services/mapserver']"]
    drawing = "service.py   the adapter\nmap.py, mapfiles.py   the map\n    and its files\nmotion.py    pure\n"
    assert drawn_rows(drawing) == {"service": 0, "map": 1, "mapfiles": 1, "motion": 2}
    imports = {"service": {"map"}, "map": {"motion"}, "mapfiles": {"map"}, "motion": set(), "stages": set()}
    assert drawing_problems(drawn_rows(drawing), imports) == ["not drawn: ['stages']"]
    imports["motion"] = {"service"}
    assert drawing_problems(drawn_rows(drawing + "stages.py  x\n"), imports) == [
        "motion.py is drawn below service.py, which it imports"]
    assert one_user_exceptions("- a rule\n- one user: `SHARED_WITH_ONE_USER` lists `shared/replicas.py` today\n"
                               "- another rule `shared/keys.py`\n") == {"replicas"}
    assert one_user_exceptions("- one user: `SHARED_WITH_ONE_USER`; none today\n\n| `shared/keys.py` |") == set()


def test_the_architecture_page_draws_the_code_as_it_is():
    """The page names every shared/ module, draws each room's files in their room and the tracker's modules in the
    order they import one another, and lists the one-user exceptions the architecture test keeps."""
    spec = importlib.util.spec_from_file_location("twohr_test_architecture", REPO / "tests" / "test_architecture.py")
    architecture = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(architecture)
    page = ARCHITECTURE.read_text()
    shared = {p.stem for p in (REPO / "shared").glob("*.py") if p.stem != "__init__"}
    problems = shared_table_problems(section(page, "## The common library"), shared)
    problems += rooms_table_problems(section(page, "## The rooms"), SERVICES)
    drawing = re.search(r"```text\n(.*?)```", section(page, "### The tracker room"), re.S).group(1)
    problems += [f"the tracker's drawing: {p}" for p in drawing_problems(drawn_rows(drawing),
                                                                         room_imports(SERVICES / "tracker"))]
    if (listed := one_user_exceptions(page)) != set(architecture.SHARED_WITH_ONE_USER):
        problems.append(f"the page lists the one-user exceptions {sorted(listed)}, the test "
                        f"{sorted(architecture.SHARED_WITH_ONE_USER)}")
    assert not problems, "\n".join(problems)
