"""``python -m twohr_services.gateway``: serve the HTTP control API with uvicorn."""

from __future__ import annotations

import ssl
from pathlib import Path

import uvicorn
from pydantic import ValidationError

from twohr.bus import bus_from_args
from twohr.errors import TwohrError, validation_problems
from twohr.service import one_line_errors, service_parser

from .admission import parse_max_robots
from .app import create_app
from .settings import GatewaySettings


def versions_kept(text: str) -> int:
    """``--map-versions``: a whole number from 1 to 10000 (argparse says so in one line otherwise)."""
    import argparse

    if not text.strip().isdigit() or not 1 <= int(text) <= 10_000:
        raise argparse.ArgumentTypeError(f"{text!r}: give the versions of each map to keep, 1 to 10000")
    return int(text)


def build_parser():
    """The gateway's command line: the options every service takes (``--router``) and its own."""
    parser = service_parser("gateway", "twohr HTTP gateway")
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=8080)
    parser.add_argument("--data-root", action="append", default=None,
                        help="folder sequences may come from (repeatable)")
    parser.add_argument("--recordings", default="recordings", help="folder the recorder writes MCAP files to")
    parser.add_argument("--api-token", default=None, help="require 'Authorization: Bearer TOKEN' on /sessions "
                        "(default $TWOHR_API_TOKEN)")
    parser.add_argument("--api-token-file", default=None, help="read the token from this file (as compose does)")
    parser.add_argument("--maps", default=None, help="the map store's folder (served on twohr/maps/<name> and "
                        "/maps); default none")
    parser.add_argument("--map-versions", type=versions_kept, default=10, metavar="N", help="versions of each map "
                        "the store keeps (default 10; past it the oldest go, the others keep their numbers)")
    parser.add_argument("--audit-log", default=None, metavar="FILE", help="the audit trail, JSON lines (default "
                        "RECORDINGS/audit.jsonl; GET /audit, the operator's token)")
    parser.add_argument("--foxglove-port", type=int, default=8765,
                        help="port of the Foxglove WebSocket live view on --host (default 8765; 0 turns it off; "
                        "with --tls-keys on TLS, and a viewer needs ?token=, a view token from GET /live)")
    parser.add_argument("--tls-keys", default=None, metavar="FOLDER", help="serve HTTPS (TLS 1.3 only) with the "
                        "certificate and key of this key folder (cert.pem, key.pem: the gateway's of a fleet's keys)")
    parser.add_argument("--max-robots", default=None, metavar="N", help="robots the stack carries at 30 Hz, or auto "
                        "(from the cores): past it POST /sessions gets 503 with Retry-After (default: no limit)")
    parser.add_argument("--robot-tokens", default=None, metavar="FILE", help="the robots' API tokens (robot -> "
                        "SHA-256 and expiry, JSON, as twohr keys writes it): each starts, stops and reads its own "
                        "sessions until its certificate expires")
    return parser


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
    return GatewaySettings(
        data_roots=[Path(r) for r in (args.data_root or ["data"])],
        recordings=Path(args.recordings),
        **({"api_token": Path(args.api_token_file).read_text().strip()} if args.api_token_file else
           {"api_token": args.api_token} if args.api_token else {}),
        bus=bus_from_args(args),
        foxglove_host=args.host,
        foxglove_port=args.foxglove_port or None,
        tls_keys=Path(args.tls_keys) if args.tls_keys else None,
        maps=Path(args.maps) if args.maps else None,
        map_versions=args.map_versions,
        audit_log=Path(args.audit_log) if args.audit_log else None,
        robot_tokens=Path(args.robot_tokens) if args.robot_tokens else None,
        max_robots=parse_max_robots(args.max_robots) if args.max_robots else None,
    )


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
