"""The import graph between the project's rooms, from grimp: which room imports which.

    .venv/bin/python -m twohr_lab.architecture --out runs/architecture

A room is ``twohr`` (shared), each service package of ``twohr_services``, the composition root ``twohr_app``
(app/: the command line, the in-process pipeline, the supervisor) and each part of ``twohr_lab``.
Writes ``import_graph.md`` (the edges, and the sideways imports between services, which must be none)
and exits 1 when a service imports another.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .stamp import stamp_line

PACKAGES = ("twohr", "twohr_services", "twohr_app", "twohr_lab")


def rooms(graph) -> dict[str, list[str]]:
    """Room name -> its modules: the common library and the composition root are one room each, every service
    package and every part of the lab is one."""
    out: dict[str, list[str]] = {top: sorted(graph.find_descendants(top) | {top})
                                 for top in ("twohr", "twohr_app") if top in graph.modules}
    for top in ("twohr_services", "twohr_lab"):
        if top not in graph.modules:
            continue
        for child in sorted(graph.find_children(top)):
            descendants = graph.find_descendants(child)
            if descendants:
                out[child] = sorted(descendants | {child})
            else:
                out.setdefault(f"{top} (top-level modules)", []).append(child)
    return out


def room_edges(graph) -> list[tuple[str, str]]:
    """(importer room, imported room) for every pair with at least one direct import."""
    members = rooms(graph)
    owner = {module: room for room, modules in members.items() for module in modules}
    edges = set()
    for module, room in owner.items():
        for imported in graph.find_modules_directly_imported_by(module):
            target = owner.get(imported)
            if target is not None and target != room:
                edges.add((room, target))
    return sorted(edges)


def sideways(edges: list[tuple[str, str]]) -> list[tuple[str, str]]:
    """Edges from one service package to another."""
    def is_service(room: str) -> bool:
        return room.startswith("twohr_services.") and "(" not in room

    return [(a, b) for a, b in edges if is_service(a) and is_service(b)]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m twohr_lab.architecture", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default="runs/architecture", help="output folder (default runs/architecture)")
    args = parser.parse_args(argv)
    import grimp

    graph = grimp.build_graph(*PACKAGES)
    edges = room_edges(graph)
    bad = sideways(edges)
    lines = [stamp_line(sys.argv[1:] if argv is None else argv, "python -m twohr_lab.architecture"), "",
             f"# Import graph between rooms (grimp {grimp.__version__}, {len(graph.modules)} modules)", "",
             "| importer | imports |", "|---|---|"]
    for importer in sorted({a for a, _ in edges}):
        lines.append(f"| {importer} | {', '.join(b for a, b in edges if a == importer)} |")
    lines += ["", f"Sideways imports between services: {len(bad)}"]
    lines += [f"- {a} -> {b}" for a, b in bad]
    text = "\n".join(lines) + "\n"
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "import_graph.md").write_text(text)
    print(text)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
