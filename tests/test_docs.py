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
