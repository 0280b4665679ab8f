"""The rooms stay rooms. Imports point one way through four layers, ``twohr`` (shared/) < the service rooms
(services/) < the composition root (app/) < the lab (lab/); no service imports another sideways; services/ holds
only service rooms; no generated results live inside the services; functions stay short where people read first."""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SERVICES = REPO / "services"
#: Each layer may import the layers below it, never one above. Tests are left out: a room's tests may compose it
#: with others through the composition root (the tracker's tests run the in-process pipeline).
LAYERS = {"twohr": (0, REPO / "shared"), "twohr_services": (1, SERVICES), "twohr_app": (2, REPO / "app"),
          "twohr_lab": (3, REPO / "lab")}


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


def product_modules():
    """(package, module name, path) of every module of the four layers, tests left out; a package's
    ``__init__`` keeps its ``.__init__`` suffix so that its relative imports resolve against the package."""
    for package, (_, folder) in LAYERS.items():
        for path in sorted(folder.rglob("*.py")):
            relative = path.relative_to(folder)
            if "tests" in relative.parts or "__pycache__" in relative.parts:
                continue
            yield package, ".".join([package, *relative.with_suffix("").parts]), path


def upward_imports(package: str, module: str, source: str) -> list[str]:
    """The imports of ``module`` (in layer ``package``) of a module in a higher layer."""
    rank = LAYERS[package][0]
    return sorted(name for name in imported_modules(source, module)
                  if name.split(".")[0] in LAYERS and LAYERS[name.split(".")[0]][0] > rank)


def test_the_layer_check_sees_an_upward_import():
    assert upward_imports("twohr_services", "twohr_services.tracker.core", "from twohr_app.pipeline import x")
    assert upward_imports("twohr", "twohr.keys", "import twohr_services.tracker")
    assert upward_imports("twohr_app", "twohr_app.commands.run", "def f():\n    from twohr_lab import bench\n")
    assert not upward_imports("twohr_app", "twohr_app.commands.run", "from ..pipeline import run_sequence\n"
                              "from twohr_services.tracker import core\nfrom twohr import keys")
    assert not upward_imports("twohr_lab", "twohr_lab.bench", "from twohr_app.pipeline import run_sequence")


def test_imports_point_one_way_through_the_layers():
    """shared < services < the composition root < the lab: no service imports the composition root, and nothing
    at run time imports the lab (it adds its commands through the ``twohr.commands`` entry-point group)."""
    modules = list(product_modules())
    assert {package for package, _, _ in modules} == set(LAYERS)
    problems = [f"{path.relative_to(REPO)} imports {name}" for package, module, path in modules
                for name in upward_imports(package, module, path.read_text())]
    assert not problems, problems


def test_services_holds_only_service_rooms():
    """The front door is easy to find: no module lies loose in services/, and the common library keeps no
    service's own package (the ROS 2 bridge lives in its room)."""
    loose = [p.name for p in SERVICES.iterdir() if p.is_file() and p.name != "__init__.py"]
    assert not loose, loose
    assert all((p / "__init__.py").is_file() for p in SERVICES.iterdir() if p.is_dir() and p.name != "__pycache__")
    assert not (REPO / "shared" / "ros2").exists()


def long_functions(folder: Path, limit: int = 80) -> list[str]:
    """``path:line name (n lines)`` of every function under ``folder`` longer than ``limit`` lines, tests aside."""
    found = []
    for path in sorted(folder.rglob("*.py")):
        if "tests" in path.relative_to(folder).parts:
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                length = node.end_lineno - node.lineno + 1
                if length > limit:
                    found.append(f"{path.relative_to(REPO)}:{node.lineno} {node.name} ({length} lines)")
    return found


def test_no_function_in_the_gateway_or_the_composition_root_is_longer_than_80_lines():
    assert long_functions(SERVICES / "tracker", limit=30)  # the check can fail
    assert not long_functions(SERVICES / "gateway") + long_functions(REPO / "app")


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

    from twohr_app.cli import COMMAND_GROUP, build_parser

    assert {entry.name for entry in entry_points(group=COMMAND_GROUP)} >= {"20-bench", "30-features", "40-yolo",
                                                                          "50-matcher"}
    parser = build_parser()
    commands = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices
    order = list(commands)
    assert order.index("run") < order.index("bench") < order.index("features") < order.index("yolo") \
        < order.index("matcher") < order.index("up") < order.index("camera")
    assert parser.parse_args(["bench", "--ablations"]).func.__module__ == "twohr_lab.bench.cli"


def test_service_rooms_hold_only_their_core_adapter_and_docs():
    """No offline studies and no generated results inside a service room."""
    for room in service_rooms():
        assert not (SERVICES / room / "results").exists(), room
        for path in (SERVICES / room).iterdir():
            assert path.name not in ("cli.py", "bench.py", "dev_run.py", "report.py", "training.py"), path


def test_every_package_folder_is_in_the_installed_wheel():
    """The image installs the project as a wheel (not editable): a package folder missing from pyproject's list
    imports here and fails only in the containers (CI once stopped on ``twohr_services.gateway.routes``)."""
    import tomllib
    listed = set(tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    folders = set()
    for package, (_, root) in LAYERS.items():
        for init in root.rglob("__init__.py"):
            parts = init.parent.relative_to(root).parts
            if "tests" not in parts and not any(p.startswith((".", "_")) for p in parts):
                folders.add(".".join([package, *parts]))
    assert folders - listed == set(), f"add to [tool.setuptools] packages: {sorted(folders - listed)}"


def import_cycles(graph, package: str) -> list[tuple[str, str]]:
    """(a, b) for every direct import a -> b inside ``package`` (its tests aside) where b also reaches a: the
    edges of import cycles, ``if TYPE_CHECKING:`` imports included (grimp counts them unless told not to)."""
    modules = {m for m in graph.find_descendants(package) if ".tests" not in m} | {package}
    return [(a, b) for a in sorted(modules) for b in sorted(graph.find_modules_directly_imported_by(a) & modules)
            if graph.chain_exists(importer=b, imported=a)]


def test_the_cycle_check_sees_a_type_checking_cycle(tmp_path, monkeypatch):
    """Today's circle was made of ``if TYPE_CHECKING:`` imports; the check below must see one."""
    import grimp
    room = tmp_path / "cyclic_room"
    room.mkdir()
    (room / "__init__.py").write_text("")
    (room / "tracking.py").write_text("from .mapping import LocalMapping\n")
    (room / "mapping.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
                                     "    from .tracking import Tracker\n")
    (room / "pose.py").write_text("import numpy\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    graph = grimp.build_graph("cyclic_room", cache_dir=None)
    assert import_cycles(graph, "cyclic_room") == [("cyclic_room.mapping", "cyclic_room.tracking"),
                                                   ("cyclic_room.tracking", "cyclic_room.mapping")]


def test_no_service_room_has_an_import_cycle():
    """Each room's files can be read, tested and replaced apart (the tracker's search lives in ``local_map``, its
    mapping worker above the tracker in ``mapper``)."""
    import grimp
    graph = grimp.build_graph("twohr_services", cache_dir=None)
    rooms = [f"twohr_services.{room}" for room in service_rooms()]
    assert {"twohr_services.tracker.local_map", "twohr_services.tracker.mapper"} <= graph.modules
    assert {room: cycles for room in rooms if (cycles := import_cycles(graph, room))} == {}


#: ``shared/`` modules with one user for now, and why they are shared all the same (none today)
SHARED_WITH_ONE_USER: dict[str, str] = {}


def shared_module_users() -> dict[str, set[str]]:
    """For each ``shared/`` module, the users that import it: a service room (``services/<room>``), ``app``,
    ``lab`` or another shared module (``shared/<name>``); tests aside."""
    shared = {p.stem for p in (REPO / "shared").glob("*.py") if p.stem != "__init__"}
    users: dict[str, set[str]] = {name: set() for name in shared}
    for package, module, path in product_modules():
        relative = path.relative_to(REPO)
        user = {"twohr": f"shared/{path.stem}", "twohr_services": f"services/{relative.parts[1]}"}.get(
            package, relative.parts[0])
        for name in imported_modules(path.read_text(), module):
            parts = name.split(".")
            if parts[0] == "twohr" and len(parts) > 1 and parts[1] in shared and user != f"shared/{parts[1]}":
                users[parts[1]].add(user)
    return users


def test_shared_keeps_only_what_two_users_need():
    """``shared/`` is the common library: a module only one room uses lives in that room."""
    users = shared_module_users()
    # the check counts rooms, not files: the tracker places keyframe jobs on replicas, twohr bench --fleet and a
    # robot's own tracker (twohr camera --edge) too
    assert users["replicas"] == {"services/tracker", "lab", "app"}
    assert {"services/tracker", "app", "lab", "shared/dataset"} <= users["geometry"]
    lonely = {name: sorted(found) for name, found in users.items() if len(found) < 2}
    assert lonely.keys() == SHARED_WITH_ONE_USER.keys(), lonely


def subclasses_of(name: str, folder: Path) -> list[str]:
    """``path:line class`` of every class under ``folder`` whose bases name ``name`` (``Name`` or ``module.Name``)."""
    found = []
    for path in sorted(folder.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ClassDef) and any(
                    (isinstance(base, ast.Name) and base.id == name) or
                    (isinstance(base, ast.Attribute) and base.attr == name) for base in node.bases):
                found.append(f"{folder.name}/{path.relative_to(folder)}:{node.lineno} {node.name}")
    return found


def test_a_robots_own_tracker_is_composed_not_a_subclass_of_the_trackers_service(tmp_path):
    """``twohr camera --edge`` builds the stack's ``TrackerService`` with its own frame inlet and stages: no class in
    app/ subclasses it (the scan sees both spellings of a base)."""
    (tmp_path / "a.py").write_text("class A(TrackerService):\n    pass\n\nclass B(service.TrackerService):\n    pass\n")
    assert [line.split(" ")[1] for line in subclasses_of("TrackerService", tmp_path)] == ["A", "B"]
    assert subclasses_of("TrackerService", SERVICES / "tracker") == []  # nor in its own room
    assert subclasses_of("TrackerService", REPO / "app") == []
