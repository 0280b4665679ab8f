"""MkDocs hook (``hooks:`` in mkdocs.yml): the pages made from code at build time, never written by hand.

- ``http-api.md`` and ``openapi.json``: the gateway's own OpenAPI schema, from its FastAPI app factory
  (``twohr_services.gateway.app.create_app``; building the app opens no bus and starts no server);
- ``bus-keys.md``: the Zenoh keys of ``twohr.keys`` (``CARRIES`` says what each carries) and which role may put,
  receive, answer or ask on each, from the roles' grants as the router's access list enforces them.

Both are added to the site's files in ``on_files`` (``File.generated``): nothing is written into docs/.
"""

from __future__ import annotations

import importlib
import json
import re

import zenoh
from mkdocs.exceptions import PluginError
from mkdocs.structure.files import File

#: the module that defines the roles' grants (``role_grants``) and turns them into the router's rules (``role_rules``)
GRANTS_MODULE = "twohr_app.access"


def on_files(files, config):
    schema = openapi_schema()
    files.append(File.generated(config, "openapi.json", content=json.dumps(schema, indent=1)))
    files.append(File.generated(config, "http-api.md", content=api_page(schema)))
    files.append(File.generated(config, "bus-keys.md", content=keys_page()))
    return files


# --- the HTTP API ---------------------------------------------------------------------------------------------------

def openapi_schema() -> dict:
    from twohr_services.gateway.app import create_app
    from twohr_services.gateway.settings import GatewaySettings

    return create_app(GatewaySettings()).openapi()


def _text(text) -> str:
    """Schema prose as Markdown: ``<`` and ``>`` outside code spans escaped (``twohr/<robot_id>/camera`` would
    read as an HTML tag)."""
    parts = re.split(r"(`+[^`]*`+)", str(text or ""))
    return "".join(part if i % 2 else part.replace("<", "&lt;").replace(">", "&gt;") for i, part in enumerate(parts))


def _cell(text) -> str:
    return " ".join(_text(text).split()).replace("|", "\\|")


def schema_name(schema: dict | None) -> str:
    """A short name for a schema: its component's name, ``list[...]``, or its JSON type."""
    if not schema:
        return "any"
    if "$ref" in schema:
        return schema["$ref"].rsplit("/", 1)[-1]
    if "anyOf" in schema:
        return " \\| ".join(schema_name(s) for s in schema["anyOf"])
    if schema.get("type") == "array":
        return f"list[{schema_name(schema.get('items'))}]"
    if schema.get("format") == "binary":
        return "bytes"
    if schema.get("title") and schema.get("properties") and not schema["title"].startswith("Response "):
        return schema["title"]  # an inline model, e.g. the error replies' Problem
    return schema.get("type", "any")


def inline_models(schema: dict) -> dict[str, dict]:
    """The named object schemas the responses carry inline (not in ``components``), by title."""
    found = {}
    for _, _, op in _operations(schema):
        for response in op["responses"].values():
            for media in (response.get("content") or {}).values():
                model = media.get("schema") or {}
                if schema_name(model) == model.get("title"):
                    found[model["title"]] = model
    return found


def _content(body: dict) -> str:
    """``schema (media type)`` for each media type of a request or response body."""
    content = body.get("content") or {}
    return ", ".join(f"`{schema_name(media.get('schema'))}` ({kind})" for kind, media in content.items()) or "none"


def _operations(schema: dict):
    for path, operations in schema["paths"].items():
        for method, operation in operations.items():
            yield method.upper(), path, operation


def api_page(schema: dict) -> str:
    info = schema["info"]
    lines = ["# HTTP API", "",
             f"{info.get('title')} (API version {info.get('version')}), OpenAPI {schema.get('openapi')}. "
             f"{_cell(info.get('description'))}", "",
             "This page is made from the gateway's own OpenAPI schema when the documentation is built; the schema "
             "itself is [openapi.json](openapi.json), and a running gateway serves it at `/openapi.json` and as "
             "interactive documentation at `/docs`. How to run the gateway and what a session does: "
             "[Microservices on Zenoh](microservices.md).", "",
             "| method | path | summary | request | success |", "|---|---|---|---|---|"]
    for method, path, op in _operations(schema):
        success = [f"{code} {_content(r)}" for code, r in op["responses"].items() if code.startswith("2")]
        request = _content(op["requestBody"]) if "requestBody" in op else "none"
        lines.append(f"| {method} | `{path}` | {_cell(op.get('summary'))} | {request} | {'; '.join(success)} |")
    lines += ["", "## Routes", ""]
    for method, path, op in _operations(schema):
        lines += [f"### {method} `{path}`", "", _cell(op.get("summary")) + ".", ""]
        if op.get("description"):
            lines += [_text(op["description"].strip()), ""]
        if op.get("parameters"):
            lines += ["| parameter | in | required | type | description |", "|---|---|---|---|---|"]
            lines += [f"| `{p['name']}` | {p['in']} | {'yes' if p.get('required') else 'no'} | "
                      f"{schema_name(p.get('schema'))} | {_cell(p.get('description'))} |" for p in op["parameters"]]
            lines.append("")
        if "requestBody" in op:
            lines += [f"Request body: {_content(op['requestBody'])}.", ""]
        lines += ["| status | meaning | body |", "|---|---|---|"]
        lines += [f"| {code} | {_cell(r.get('description'))} | {_content(r)} |" for code, r in op["responses"].items()]
        lines.append("")
    lines += ["## Schemas", ""]
    for name, component in {**schema.get("components", {}).get("schemas", {}), **inline_models(schema)}.items():
        lines += [f"### {name}", "", _cell(component.get("description")), "",
                  "| field | type | required | description |", "|---|---|---|---|"]
        required = set(component.get("required", []))
        lines += [f"| `{field}` | {schema_name(spec)} | {'yes' if field in required else 'no'} | "
                  f"{_cell(spec.get('description'))} |" for field, spec in component.get("properties", {}).items()]
        lines.append("")
    return "\n".join(lines)


# --- the bus keys ---------------------------------------------------------------------------------------------------

def grants_module():
    module = importlib.import_module(GRANTS_MODULE)
    if not (hasattr(module, "role_grants") and hasattr(module, "role_rules")):
        raise PluginError(f"docs/hooks.py: {GRANTS_MODULE} defines no role_grants and role_rules; point "
                          "GRANTS_MODULE at the module that does")
    return module


#: what a role does on a key, by the router's ACL messages it sends (its ingress)
ACTIONS = {"put": "put", "declare_subscriber": "receive", "declare_queryable": "answer", "query": "ask",
           "liveliness_token": "hold", "declare_liveliness_subscriber": "watch"}
#: the two columns of each kind of key: (who makes it, who takes it)
KINDS = {"data": ("put", "receive"), "query": ("answer", "ask"), "token": ("hold", "watch")}


def key_rows(keys) -> list[tuple[str, str, str, str]]:
    """(shown key, key matched against the grants, kind, name in ``keys.CARRIES``) of every key ``twohr.keys``
    defines. A robot's keys are matched as one robot's (``robot1``): a wildcard would also match ``_health``."""
    robot = [(s, "data") for s in (keys.CONTROL, keys.RAW_CAMERA, *keys.STREAMS)]
    queries = [keys.DETECT_QUERY, keys.DYNAMICS_QUERY, keys.MATCH_QUERY]
    rows = [(f"{keys.PREFIX}/<robot>/{s}", keys.key("robot1", s), kind, s) for s, kind in robot]
    rows += [(f"{keys.PREFIX}/<robot>/{q}/<replica>", keys.replica_query("robot1", q, "replica1"), "query", q)
             for q in queries]
    rows += [(f"{keys.HEALTH_PREFIX}/<service>/<replica>", keys.health_key("*"), "query", keys.HEALTH_PREFIX),
             (f"{keys.ALIVE_PREFIX}/<service>/<replica>", keys.alive_key("*"), "token", keys.ALIVE_PREFIX),
             (keys.map_key("<name>"), keys.map_key("lab"), "query", keys.MAPS_PREFIX),
             (keys.map_key("<name>", save=True), keys.map_key("lab", save=True), "query", f"{keys.MAPS_PREFIX}/save"),
             (keys.merged_key("<name>"), keys.merged_key("lab"), "data", f"{keys.MAPS_PREFIX}/merged")]
    # a snapshot is put by the tracker and kept by the map room, which answers it to the tracker a session moves to
    rows += [(keys.snapshot_key("<robot>"), keys.snapshot_key("robot1"), kind, keys.SNAPSHOT)
             for kind in ("data", "query")]
    named = {name for *_, name in rows}
    defined = {value for name, value in vars(keys).items() if isinstance(value, str) and (
        name.endswith(("_QUERY", "_PREFIX")) and name != "PREFIX" or name in ("CONTROL", "RAW_CAMERA"))}
    missing = sorted((defined | set(keys.STREAMS) | set(keys.CARRIES)) - named) + sorted(named - set(keys.CARRIES))
    if missing:
        raise PluginError(f"docs/hooks.py: the key table and twohr.keys disagree on {missing}: give each key a row "
                          "here and a line in twohr.keys.CARRIES")
    return rows


def who(rules_by_role: dict[str, list[dict]], key_expr: str) -> dict[str, list[str]]:
    """action -> the roles whose ACL rules let them do it on (some of) ``key_expr``."""
    found: dict[str, list[str]] = {action: [] for action in ACTIONS.values()}
    wanted = zenoh.KeyExpr(key_expr)
    for role, rules in rules_by_role.items():
        for action in {ACTIONS[m] for rule in rules if "ingress" in rule["flows"] for m in rule["messages"]
                       if m in ACTIONS and any(zenoh.KeyExpr(k).intersects(wanted) for k in rule["key_exprs"])}:
            found[action].append(role)
    return found


def _roles(roles: list[str], everyone: set[str]) -> str:
    return "every role" if set(roles) == everyone else ", ".join(sorted(roles)) or "—"


def keys_page() -> str:
    from twohr import keys

    access = grants_module()
    grants = access.role_grants()
    rules_by_role = {role: access.role_rules(role, g) for role, g in grants.items()}
    everyone = set(rules_by_role)
    lines = ["# Bus keys", "",
             "Every key twohr uses on Zenoh, and which roles the router lets put, receive, answer or ask on it. "
             f"This page is made when the documentation is built: the keys from `twohr.keys` (`shared/keys.py`), "
             f"the roles' grants from `{access.__name__}` (`role_grants`, turned into the router's access list by "
             "`role_rules`), so it says what the router enforces.", "",
             "| key | what it carries | put / answer / hold | receive / ask / watch |", "|---|---|---|---|"]
    for shown, key_expr, kind, name in key_rows(keys):
        make, take = KINDS[kind]
        found = who(rules_by_role, key_expr)
        lines.append(f"| `{shown}` | {_cell(keys.CARRIES[name])} | {make}: {_roles(found[make], everyone)} | "
                     f"{take}: {_roles(found[take], everyone)} |")
    lines += ["", f"The roles: {', '.join(f'`{r}`' for r in grants)}. A service process joins as its service's role; "
              "`client` is everything outside the stack (camera drivers, other robots, viewers, ROS 2 nodes, "
              "`twohr health`), and `router` a robot's own router linked to the stack's, with a client's grants. "
              "In a fleet (`twohr up --keys`), each robot is its own subject with a client's grants, except that it "
              "may put only its own camera (`twohr/<robot>/camera`), may neither ask the services' health nor watch "
              "their liveliness (both name every replica and its host), and of ROS 2 it uses its own namespace and "
              "reads "
              "the others' poses, odometry, paths and transforms only; see [Fleet](fleet.md#threat-model). "
              "The ros2 service and clients are also granted rmw_zenoh's keys of one ROS 2 domain "
              "([ROS 2](ros2.md)). What a message holds: [Microservices on Zenoh](microservices.md#messages).", ""]
    return "\n".join(lines)
