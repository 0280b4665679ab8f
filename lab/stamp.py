"""Provenance of a study's outputs: the commit and the exact command that made them."""

from __future__ import annotations

import json
import shlex
import subprocess
import sys
from datetime import UTC, datetime
from pathlib import Path

from twohr.machine import machine

REPO_ROOT = Path(__file__).resolve().parents[1]


def _git(*args: str) -> str | None:
    try:
        done = subprocess.run(["git", "-C", str(REPO_ROOT), *args], capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return done.stdout.strip() if done.returncode == 0 else None


def provenance(argv: list[str] | None = None, program: str = "twohr") -> dict[str, object]:
    """The commit (with ``+dirty`` for uncommitted changes), the command line and the time, as a dict."""
    argv = sys.argv[1:] if argv is None else argv
    commit = _git("rev-parse", "HEAD") or "unknown (not a git checkout)"
    if _git("status", "--porcelain", "--untracked-files=no"):
        commit += "+dirty"
    return {"commit": commit, "command": " ".join([program, shlex.join(argv)]).strip(),
            "made_at": datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ"), "machine": machine()}


def write_stamp(out: str | Path, argv: list[str] | None = None, program: str = "twohr") -> Path:
    """Write ``stamp.json`` (see :func:`provenance`) into the output folder ``out``."""
    path = Path(out) / "stamp.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(provenance(argv, program), indent=2) + "\n")
    return path


def stamp_line(argv: list[str] | None = None, program: str = "twohr") -> str:
    """One Markdown line for the top of a report: ``Made by `command` at commit X.``"""
    return _made_by(provenance(argv, program))


def _made_by(stamp: dict[str, object]) -> str:
    return f"Made by `{stamp['command']}` at commit {stamp['commit']}, {stamp['made_at']}."


def write_study(out: str | Path, name: str, markdown: str, rows: list, argv: list[str] | None = None,
                program: str = "twohr") -> Path:
    """A study's two outputs in the folder ``out``: ``<name>.md`` (the stamp line, then ``markdown``) and
    ``<name>.json`` (the provenance and ``rows``). Returns the folder."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    stamp = provenance(argv, program)
    (out / f"{name}.md").write_text(f"{_made_by(stamp)}\n\n{markdown}\n")
    (out / f"{name}.json").write_text(json.dumps({"provenance": stamp, "rows": rows}, indent=2))
    return out
