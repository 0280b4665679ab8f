"""The rooms stay rooms: no service imports another sideways, the runtime never imports the lab, and no
generated results live inside the services."""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SERVICES = REPO / "services"


def imported_modules(source: str, module: str) -> set[str]:
    """Absolute names of the modules that ``source`` (the text of module ``module``) imports, relative
    imports resolved against ``module``'s package."""
    package = module.split(".")[:-1]
    found = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = package[:len(package) - node.level + 1] if node.level else []
            name = ".".join([*base, *([node.module] if node.module else [])])
            found.add(name)
            found.update(f"{name}.{alias.name}" for alias in node.names)  # `from . import x` imports module x
    return found


def service_rooms() -> list[str]:
    return sorted(p.name for p in SERVICES.iterdir() if (p / "__init__.py").is_file())


def room_modules(room: str):
    """(module name, path) of every module of a service room, its tests aside."""
    for path in sorted((SERVICES / room).rglob("*.py")):
        if "tests" in path.relative_to(SERVICES / room).parts:
            continue
        parts = path.relative_to(SERVICES).with_suffix("").parts
        yield ".".join(["twohr_services", *parts]), path


def sideways_imports(room: str, rooms: list[str], module: str, source: str) -> list[str]:
    others = {f"twohr_services.{other}" for other in rooms if other != room}
    return sorted(name for name in imported_modules(source, module)
                  if any(name == o or name.startswith(o + ".") for o in others))


def test_the_import_parser_sees_sideways_imports():
    """The check below must be able to fail: every spelling of an import of another room is caught."""
    rooms = ["detector", "matcher"]
    module = "twohr_services.matcher.cli"
    for source in ("from twohr_services.detector.core import build_detector",
                   "import twohr_services.detector.core",
                   "from ..detector import core",
                   "from .. import detector",
                   "def f():\n    from ..detector.core import build_detector\n"):
        assert sideways_imports("matcher", rooms, module, source), source
    assert not sideways_imports("matcher", rooms, module, "from .core import mutual_nn\nfrom twohr.pairs import x")


def test_no_service_imports_another_service():
    rooms = service_rooms()
    assert {"detector", "yolo", "matcher", "tracker", "source", "recorder", "gateway"} <= set(rooms)
    problems = [f"{path.relative_to(REPO)} imports {name}"
                for room in rooms for module, path in room_modules(room)
                for name in sideways_imports(room, rooms, module, path.read_text())]
    assert not problems, problems


def test_the_runtime_does_not_import_the_lab():
    """No service module imports the lab, the command line (services/cli.py) included: the lab adds its
    subcommands through the ``twohr.commands`` entry-point group."""
    for path in sorted(SERVICES.rglob("*.py")):
        if "tests" in path.parts:
            continue
        module = ".".join(["twohr_services", *path.relative_to(SERVICES).with_suffix("").parts])
        assert not any(n.split(".")[0] == "twohr_lab" for n in imported_modules(path.read_text(), module)), path


def test_no_file_under_services_names_the_lab_package():
    """Like ``git grep twohr_lab -- services/``: no module, test, README or data file names the lab's package
    (docs point at the lab's folders, lab/...; caches of compiled modules aside)."""
    files = [path for path in sorted(SERVICES.rglob("*"))
             if path.is_file() and "__pycache__" not in path.parts and path.suffix != ".pyc"]
    assert len(files) > 50
    assert not [str(path.relative_to(REPO)) for path in files if b"twohr_lab" in path.read_bytes()]


def test_the_lab_still_adds_its_commands():
    """bench, features, yolo and matcher come through the entry points, in their place in ``twohr --help``."""
    import argparse
    from importlib.metadata import entry_points

    from twohr_services.cli import COMMAND_GROUP, build_parser

    assert {entry.name for entry in entry_points(group=COMMAND_GROUP)} >= {"20-bench", "30-features", "40-yolo",
                                                                          "50-matcher"}
    parser = build_parser()
    commands = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices
    order = list(commands)
    assert order.index("run") < order.index("bench") < order.index("features") < order.index("yolo") \
        < order.index("matcher") < order.index("up") < order.index("camera")
    assert parser.parse_args(["bench", "--ablations"]).func.__module__ == "twohr_lab.bench_cli"


def test_service_rooms_hold_only_their_core_adapter_and_docs():
    """No offline studies and no generated results inside a service room."""
    for room in service_rooms():
        assert not (SERVICES / room / "results").exists(), room
        for path in (SERVICES / room).iterdir():
            assert path.name not in ("cli.py", "bench.py", "dev_run.py", "report.py", "training.py"), path
