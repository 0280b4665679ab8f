"""twohr's credentials, made, kept and written in one place.

- :mod:`.credentials`: the one password and token generator, the one private-file writer, the one users-list
  writer, the service roles, the per-role passwords of a plain (loopback) ``twohr up`` and outside clients'
  configs;
- :mod:`.certificates`: a fleet's CA and its certificates (X.509);
- :mod:`.store`: a fleet's keys folder (:class:`Fleet`, what ``twohr keys`` and ``twohr up --keys`` use).

Who may do what with these credentials, the routers' access-control lists, is :mod:`twohr_app.access`.
"""

from .certificates import pem
from .credentials import (
    CLIENT_ROLE,
    SERVICE_ROLES,
    USERS_FILE,
    Credentials,
    client_config,
    new_secret,
    password_file,
    private_folder,
    read_users,
    reveal,
    token_digest,
    write_client_config,
    write_private,
    write_users,
)
from .store import (
    LOCAL_NAMES,
    SERVING_ROLES,
    WILDCARDS,
    Fleet,
    FleetError,
    FleetFile,
    ReplicaRecord,
    RobotRecord,
    check_robot_id,
)

__all__ = ["CLIENT_ROLE", "LOCAL_NAMES", "SERVICE_ROLES", "SERVING_ROLES", "USERS_FILE", "WILDCARDS", "Credentials",
           "Fleet", "FleetError", "FleetFile", "ReplicaRecord", "RobotRecord",
           "check_robot_id", "client_config",
           "new_secret", "password_file", "pem", "private_folder", "read_users", "reveal", "token_digest",
           "write_client_config", "write_private", "write_users"]
