"""``python -m twohr_services.gateway``: serve the HTTP control API with uvicorn."""

from __future__ import annotations

import argparse
import ssl
import typing
from pathlib import Path

import uvicorn
from pydantic import ValidationError
from pydantic_core import PydanticUndefined

from twohr.bus import bus_from_args
from twohr.errors import TwohrError, validation_problems
from twohr.service import one_line_errors, service_parser

from .admission import parse_max_robots
from .app import create_app
from .settings import GatewaySettings


def versions_kept(text: str) -> int:
    """``--map-versions``: a whole number from 1 to 10000 (argparse says so in one line otherwise)."""
    if not text.strip().isdigit() or not 1 <= int(text) <= 10_000:
        raise argparse.ArgumentTypeError(f"{text!r}: give the versions of each map to keep, 1 to 10000")
    return int(text)


#: what every setting's flag is, beyond what its field says (``--<field-name>``, its type, its description): each
#: key a field of :class:`GatewaySettings` (checked when the parser is built)
FLAGS: dict[str, dict] = {
    "data_roots": {"flag": "--data-root", "action": "append", "metavar": "FOLDER", "note": "repeatable; default data"},
    "recordings": {"metavar": "FOLDER", "note": "default recordings"},
    "api_token": {"metavar": "TOKEN", "note": "default $TWOHR_API_TOKEN; or --api-token-file"},
    "robot_tokens": {"metavar": "FILE"},
    "max_robots": {"type": str, "metavar": "N", "note": "a number (auto: twohr up's, measured); default no limit"},
    "foxglove_host": {"metavar": "HOST", "note": "default: --host"},
    "foxglove_port": {"default": 8765, "metavar": "PORT", "note": "default 8765; 0 turns it off; with --tls-keys "
                      "on TLS, and a viewer needs ?token=, a view token from GET /live"},
    "tls_keys": {"metavar": "FOLDER"},
    "maps": {"metavar": "DIR"},
    "map_versions": {"type": versions_kept, "metavar": "N"},
    "map_grants": {"metavar": "FILE"},
    "audit_log": {"metavar": "FILE"},
}
#: settings that are not one flag of their own, and what sets them
NOT_FLAGS = {"bus": "--router and --keys (the options every service takes) and the environment"}


def build_parser():
    """The gateway's command line: the options every service takes (``--router``), the server's own (``--host``,
    ``--port``, ``--api-token-file``) and one flag per field of :class:`GatewaySettings`, made from the fields."""
    parser = service_parser("gateway", "twohr HTTP gateway")
    parser.add_argument("--host", default="127.0.0.1", help="interface the HTTP API (and the live view) listen on "
                        "(default 127.0.0.1)")
    parser.add_argument("--port", type=int, default=8080, help="port of the HTTP API (default 8080)")
    parser.add_argument("--api-token-file", default=None, metavar="FILE",
                        help="read --api-token from this file (as compose does)")
    add_settings_flags(parser)
    return parser


def add_settings_flags(parser: argparse.ArgumentParser) -> None:
    """One flag per field of :class:`GatewaySettings` (but :data:`NOT_FLAGS`), its help the field's description:
    ``--<name>``, of the field's type, absent unless given (the field's default, or its environment, then holds)."""
    fields = GatewaySettings.model_fields
    if stale := sorted((set(FLAGS) | set(NOT_FLAGS)) - set(fields)):
        raise TypeError(f"FLAGS name no setting: {stale}")
    for name, field in fields.items():
        if name in NOT_FLAGS:
            continue
        spec = dict(FLAGS.get(name, {}))
        flag, note = spec.pop("flag", "--" + name.replace("_", "-")), spec.pop("note", None)
        kind = _flag_type(field.annotation)
        if kind is bool:
            spec.setdefault("action", argparse.BooleanOptionalAction)
        else:
            spec.setdefault("type", kind)
        if note is None and field.default not in (None, PydanticUndefined):
            note = f"default {field.default}"
        text = " ".join(part for part in (field.description or "", f"({note})" if note else "") if part)
        parser.add_argument(flag, dest=name, default=spec.pop("default", None), help=text.replace("%", "%%"), **spec)


def _flag_type(annotation) -> type:
    """What a flag of a field annotated ``annotation`` parses: its type without None (a list's items), else str."""
    members = [arg for arg in typing.get_args(annotation) if arg is not type(None)] or [annotation]
    if len(members) == 1 and typing.get_origin(members[0]) is list:
        members = list(typing.get_args(members[0]))
    return members[0] if len(members) == 1 and members[0] in (bool, int, float, Path) else str


def settings_from_args(args) -> GatewaySettings:
    """The gateway's settings from its parsed command line; :class:`TwohrError` (one line) for settings that cannot
    be, such as a blank or short API token."""
    try:
        return _settings(args)
    except ValidationError as exc:
        raise TwohrError(f"invalid settings: {validation_problems(exc)}") from None
    except OSError as exc:
        raise TwohrError(f"--api-token-file {args.api_token_file}: {exc.strerror or exc}") from None


def _settings(args) -> GatewaySettings:
    given = {name: getattr(args, name) for name in GatewaySettings.model_fields
             if name not in NOT_FLAGS and getattr(args, name, None) is not None}
    if args.api_token_file:
        given["api_token"] = Path(args.api_token_file).read_text().strip()
    if "max_robots" in given:
        given["max_robots"] = parse_max_robots(given["max_robots"])
    given["foxglove_port"] = given.get("foxglove_port") or None  # 0: off
    given.setdefault("foxglove_host", args.host)
    return GatewaySettings(**given, bus=bus_from_args(args))


def tls13_only(config: uvicorn.Config, default) -> ssl.SSLContext:
    """uvicorn's SSL context (``ssl_context_factory``), refusing any client below TLS 1.3, as the bus's links do."""
    context = default()
    context.minimum_version = ssl.TLSVersion.TLSv1_3
    return context


@one_line_errors("gateway")
def main(argv: list[str] | None = None) -> None:
    """Parse ``argv`` (default: the process's arguments) and serve the gateway until it is stopped."""
    parser = build_parser()
    args = parser.parse_args(argv)
    tls = {}
    if args.tls_keys:
        folder = Path(args.tls_keys)
        tls = {"ssl_certfile": str(folder / "cert.pem"), "ssl_keyfile": str(folder / "key.pem")}
        missing = [path for path in tls.values() if not Path(path).is_file()]
        if missing:
            parser.exit(2, f"gateway: error: --tls-keys {args.tls_keys} lacks {', '.join(missing)}\n")
        tls["ssl_context_factory"] = tls13_only
    uvicorn.run(create_app(settings_from_args(args)), host=args.host, port=args.port, log_level="info", **tls)


if __name__ == "__main__":
    main()
