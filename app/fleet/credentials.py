"""Every credential twohr makes, and the one way each kind is written.

- :func:`new_secret`: every password and token;
- :func:`write_private`: every file that holds a secret, readable by its owner only from its first byte;
- :func:`write_users`: every router's users list (``users.txt``, Zenoh's ``user:password`` dictionary);
- :data:`SERVICE_ROLES`: the stack's own processes, each a bus user (and, on a fleet's keys, a certificate);
- :class:`Credentials`: the per-role passwords of a plain (loopback) ``twohr up``;
- :func:`write_client_config`: an outside client's Zenoh config, with its password.

A fleet's certificates are made in :mod:`.certificates` and kept by :class:`~.store.Fleet`, which writes its
secrets through these same functions.
"""

from __future__ import annotations

import contextlib
import datetime
import hashlib
import json
import os
import secrets
import stat
from collections.abc import Mapping
from pathlib import Path

from pydantic import BaseModel, SecretStr

from twohr.errors import TwohrError
from twohr.files import replacing
from twohr.keys import PIPELINE_SERVICES

#: The stack's own processes: one bus user each, and on a fleet's keys one certificate each. The router and the
#: gateway also serve TLS (the bus, HTTPS). On a plain ``twohr up``, ``router`` is the user a robot's own router
#: links in as.
SERVICE_ROLES = ("router", "gateway", *PIPELINE_SERVICES, "ros2")
#: The one user every outside client of a plain ``twohr up`` shares (camera drivers, viewers, ROS 2 nodes).
CLIENT_ROLE = "client"
USERS_FILE = "users.txt"


def new_secret(nbytes: int = 24) -> str:
    """A new password or token: ``nbytes`` random bytes from :mod:`secrets`, URL-safe base64 (no ``:``, which
    the users list uses as its separator)."""
    return secrets.token_urlsafe(nbytes)


def token_digest(token: str) -> str:
    """The SHA-256 (hex) under which a gateway knows an API token."""
    return hashlib.sha256(token.encode()).hexdigest()


def private_folder(path: Path) -> Path:
    """``path``, made if missing, readable by its owner only (0700); a folder already there is narrowed to its
    owner's bits, never widened."""
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True, mode=0o700)
    mode = path.stat().st_mode & 0o777
    if mode & 0o077:
        path.chmod(mode & 0o700)
    return path


def write_private(path: Path, text: str, keep_owner: bool = True) -> Path:
    """Write ``text`` to ``path``, readable by its owner only (0600) from its first byte, whatever the umask.

    The text goes to a new file in the same folder (``mkstemp``: ``O_CREAT | O_EXCL``, mode 0600), which then
    replaces ``path`` at once: a reader sees the old file or the new one, never half of one, and a file replaced
    is never widened. With ``keep_owner``, a regular file replaced keeps its owner when we may give it: the
    service that reads it (in a container) may run as another user than whoever runs ``twohr keys``. Without it
    (a file we hand out, such as a robot's bundle, perhaps in a folder others write to) the new file is ours,
    whoever owned what was there. A symbolic link at ``path`` is never followed: it is refused in one line."""
    path = Path(path)
    if path.is_symlink():
        raise TwohrError(f"{path} is a symbolic link: a secret is written to a file of its own, never through a "
                         "link (remove it, or name the file it points to)")
    # the rename replaces whatever is at ``path`` by then (a link planted since)
    with replacing(path, 0o600, folder_mode=0o700) as new:
        new.write(text.encode("utf-8"))
        if keep_owner:
            _keep_owner(path, new.fileno())
    return path


def _keep_owner(path: Path, tmp: int) -> None:
    """Give ``tmp`` (a file descriptor) the owner of the regular file at ``path``, if there is one (never a link's
    target's)."""
    try:
        before = os.lstat(path)
    except FileNotFoundError:
        return
    if not stat.S_ISREG(before.st_mode):
        return
    with contextlib.suppress(PermissionError):  # not root: the file becomes ours, as it would be anyway
        os.chown(tmp, before.st_uid, before.st_gid)


def users_text(users: Mapping[str, str]) -> str:
    """Zenoh's ``usrpwd`` dictionary: one ``user:password`` line per user."""
    for user, password in users.items():
        if not user or ":" in user or "\n" in user + password:
            raise ValueError(f"user {user!r}: a users list takes no ':' in a name and no line break")
    return "".join(f"{user}:{password}\n" for user, password in users.items())


def write_users(path: Path, users: Mapping[str, str]) -> Path:
    """Write a router's users list (private): every ``users.txt`` twohr makes is written here."""
    return write_private(path, users_text(users))


def read_users(path: Path) -> dict[str, str]:
    """A users list as :func:`write_users` wrote it: user -> password."""
    lines = Path(path).read_text().splitlines()
    return dict(line.split(":", 1) for line in lines if line.strip())


def reveal(model: BaseModel) -> dict:
    """A model as JSON data with its secrets written out, for the private files that must hold them."""
    def plain(value):
        if isinstance(value, dict):
            return {k: plain(v) for k, v in value.items()}
        if isinstance(value, SecretStr):
            return value.get_secret_value()
        if isinstance(value, datetime.datetime):
            return value.isoformat()
        return value

    return plain(model.model_dump())


def password_file(folder: Path, role: str) -> Path:
    """Where :meth:`Credentials.save` keeps the password of ``role`` (what ``TWOHR_ZENOH_PASSWORD_FILE`` names)."""
    return Path(folder) / f"{role}.password"


class Credentials(BaseModel):
    """One bus password per role of a plain ``twohr up``: each service role and the shared ``client``."""

    passwords: dict[str, str]

    @classmethod
    def generate(cls) -> Credentials:
        return cls(passwords={role: new_secret() for role in (*SERVICE_ROLES, CLIENT_ROLE)})

    def save(self, folder: Path) -> Path:
        """Write the router's ``users.txt`` and one ``<role>.password`` per role into ``folder`` (private, 0700),
        all private; returns the users list's path."""
        folder = private_folder(folder)
        for role, password in self.passwords.items():
            write_private(password_file(folder, role), password)
        return write_users(folder / USERS_FILE, self.passwords)


def client_config(endpoint: str, user: str, password: str) -> dict:
    """A Zenoh client configuration for ``user`` on the router at ``endpoint`` (what ``--write-client-config``
    writes and what ``BusConfig.from_file`` reads)."""
    return {
        "mode": "client",
        "connect": {"endpoints": [endpoint]},
        "scouting": {"multicast": {"enabled": False}},
        # no shared memory with the stack: an outside client's memory is not ours to map, and every client process
        # that sent through shared memory left its pool (about 19 MB) mapped in each receiver for good
        "transport": {"auth": {"usrpwd": {"user": user, "password": password}}, "shared_memory": {"enabled": False}},
    }


def write_client_config(path: Path, endpoint: str, credentials: Credentials, role: str = CLIENT_ROLE) -> Path:
    """Write a private (0600) JSON5 client config for ``role``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    header = "// twohr: a Zenoh client of the twohr router, with its credentials. Keep it private.\n"
    return write_private(path, header + json.dumps(client_config(endpoint, role, credentials.passwords[role]),
                                                   indent=2))
