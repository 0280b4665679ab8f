"""The one credential module (twohr_app.fleet): secrets are private from their first byte, whatever the umask,
and never widened; the users list round-trips; one list of roles behind the passwords and the access list."""

from __future__ import annotations

import json
import os
import stat
import tempfile

import pytest

from twohr_app.access import role_grants
from twohr_app.fleet import (
    CLIENT_ROLE,
    SERVICE_ROLES,
    USERS_FILE,
    Credentials,
    new_secret,
    password_file,
    read_users,
    write_client_config,
    write_private,
    write_users,
)
from twohr_app.fleet.credentials import users_text


def mode(path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


@pytest.fixture
def open_umask():
    """A umask that would leave every new file world-readable and writable."""
    before = os.umask(0o000)
    try:
        yield
    finally:
        os.umask(before)


def test_a_private_file_is_0600_from_its_creation_on(tmp_path, monkeypatch, open_umask):
    seen = {}
    mkstemp, replace = tempfile.mkstemp, os.replace

    def spy_mkstemp(*args, **kwargs):
        fd, name = mkstemp(*args, **kwargs)
        seen["created"] = stat.S_IMODE(os.fstat(fd).st_mode)  # before a byte is written
        seen["folder"] = os.path.dirname(name)
        return fd, name

    def spy_replace(src, dst):
        seen["written"] = mode(src)  # the moment before it takes the place of the old file
        replace(src, dst)

    monkeypatch.setattr(tempfile, "mkstemp", spy_mkstemp)
    monkeypatch.setattr(os, "replace", spy_replace)
    path = write_private(tmp_path / "secret", "s3cret")
    assert seen == {"created": 0o600, "folder": str(tmp_path), "written": 0o600}
    assert mode(path) == 0o600 and path.read_text() == "s3cret"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["secret"]  # no temporary file left


def test_overwriting_a_private_file_never_widens_it(tmp_path, open_umask):
    path = write_private(tmp_path / "secret", "one")
    write_private(path, "two")
    assert mode(path) == 0o600 and path.read_text() == "two"
    shared = tmp_path / "shared"
    shared.write_text("readable by all")
    shared.chmod(0o644)
    write_private(shared, "now private")
    assert mode(shared) == 0o600 and shared.read_text() == "now private"


def test_a_failed_write_keeps_the_old_file_and_leaves_nothing_behind(tmp_path):
    path = write_private(tmp_path / "secret", "old")
    with pytest.raises(UnicodeEncodeError):
        write_private(path, "\ud800")
    assert path.read_text() == "old" and sorted(p.name for p in tmp_path.iterdir()) == ["secret"]


def test_a_secret_is_never_written_through_a_link(tmp_path):
    from twohr.errors import TwohrError

    target = tmp_path / "target"
    target.write_text("someone's file")
    link = tmp_path / "link"
    link.symlink_to(target)
    for keep_owner in (True, False):
        with pytest.raises(TwohrError, match="is a symbolic link"):
            write_private(link, "s3cret", keep_owner=keep_owner)
    assert target.read_text() == "someone's file" and link.is_symlink()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link", "target"]  # no temporary file left


def test_the_users_list_round_trips(tmp_path, open_umask):
    users = {"tracker": new_secret(), "robot-7": new_secret(), "client": "pa=ss/word+"}
    path = write_users(tmp_path / USERS_FILE, users)
    assert read_users(path) == users and mode(path) == 0o600
    assert path.read_text().splitlines() == [f"{user}:{password}" for user, password in users.items()]
    for bad in ({"a:b": "pw"}, {"a": "pw\nroot:pw"}, {"": "pw"}):
        with pytest.raises(ValueError):
            users_text(bad)


def test_secrets_are_new_each_time_and_fit_a_users_list():
    made = {new_secret() for _ in range(100)}
    assert len(made) == 100 and all(len(s) == 32 and ":" not in s and "\n" not in s for s in made)
    assert len(new_secret(18)) == 24


def test_one_list_of_roles_behind_the_passwords_and_the_access_list():
    credentials = Credentials.generate()
    assert set(credentials.passwords) == {*SERVICE_ROLES, CLIENT_ROLE} == set(role_grants())
    assert len(set(credentials.passwords.values())) == len(credentials.passwords)


def test_a_plain_stacks_credentials_are_written_private(tmp_path, open_umask):
    credentials = Credentials.generate()
    users = credentials.save(tmp_path / "secrets")
    assert users == tmp_path / "secrets" / USERS_FILE and read_users(users) == credentials.passwords
    assert mode(tmp_path / "secrets") == 0o700
    for role, password in credentials.passwords.items():
        assert password_file(users.parent, role).read_text() == password
        assert mode(password_file(users.parent, role)) == 0o600
    config = write_client_config(tmp_path / "out" / "client.json5", "tcp/127.0.0.1:7447", credentials)
    assert mode(config) == 0o600
    body = json.loads(config.read_text().split("\n", 1)[1])
    assert body["transport"]["auth"]["usrpwd"] == {"user": "client", "password": credentials.passwords["client"]}
