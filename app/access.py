"""Who may do what on the bus: each role's grants and the router's access-control list. The roles' credentials
(passwords, users lists, certificates) are made and written by :mod:`twohr_app.fleet`.

Every process joins the router with a user name and password (Zenoh's ``usrpwd`` authentication); the
user name is its role. The router's access-control list, made here from :data:`GRANTS`, denies everything
that a role was not granted: only the tracker may publish poses, only the gateway may start or stop a
session, only the pipeline services may report a session's status, and an outside ``client`` (another
robot, a camera driver, a ROS 2 node, a viewer, ``twohr health``) may publish camera frames, read results, fetch
the map store's maps (``twohr/maps/<name>``), ask the services' health and watch their liveliness, nothing more;
only the map server (the map room) serves the maps and the sessions' map snapshots, and only the tracker may save a
map (``twohr/maps/<name>/save``) or send and fetch a snapshot. On a fleet's keys each robot has less than a client
(:func:`robot_grants`), and a robot's own tracker publishes that robot's results and status, no more.
A client that presents no credentials, or wrong ones, cannot connect at all.

Across hosts, a robot's own router links to the stack's router as the ``router`` role, which may forward what a
``client`` may do and nothing more; the robot's router grants the stack's router (its ``uplink``, known by its Zenoh
id) the mirror of that: results out to its clients, camera frames in.
"""

from __future__ import annotations

from pydantic import BaseModel, Field

from twohr.bus import endpoint_host, is_loopback_host
from twohr.keys import (
    ALIVE_PREFIX,
    CONTROL,
    DETECT_QUERY,
    DYNAMICS_QUERY,
    HEALTH_PREFIX,
    MAPS_PREFIX,
    MATCH_QUERY,
    NETWORK_SERVICES,
    PREFIX,
    RAW_CAMERA,
    alive_key,
    edge_replica,
    health_key,
    key,
    merged_key,
    snapshot_key,
)

#: rmw_zenoh's liveliness space (``twohr_services.ros2.rmw.ADMIN_SPACE``)
ADMIN_SPACE_ROS2 = "@ros2_lv"


def _robots(*streams: str) -> list[str]:
    return [f"{PREFIX}/*/{stream}" for stream in streams]


class Grants(BaseModel):
    """What one role may do, as key expressions."""

    publish: list[str] = Field(default_factory=list, description="keys it may put on")
    subscribe: list[str] = Field(default_factory=list, description="keys it may receive")
    serve: list[str] = Field(default_factory=list, description="keys it may answer queries on")
    ask: list[str] = Field(default_factory=list, description="keys it may query")
    watch_liveliness: bool = Field(False, description="may follow which services are alive")
    read_health: bool = Field(True, description="may ask the services' health counters (``twohr/_health/**``), "
                              "which name every replica and its host")
    matching: list[str] | None = Field(None, description="subscriber declarations it may learn of, so that it sends "
                                       "what it publishes at all (default: its publish keys); a robot learns of "
                                       "every camera subscriber, since they subscribe to all cameras at once")
    tokens: list[str] = Field(default_factory=list, description="liveliness tokens it may hold besides its role's "
                              "(rmw_zenoh's of its ROS 2 nodes and endpoints; a robot's own tracker's)")
    watch: list[str] = Field(default_factory=list, description="liveliness tokens it may follow, where "
                             "watch_liveliness does not give it all")


def ros2_keys(domain: int) -> list[str]:
    """rmw_zenoh's keys of one ROS 2 domain: ``<domain>/<topic>/<type>/<hash>`` data and its liveliness tokens."""
    return [f"{domain}/**", f"@ros2_lv/{domain}/**"]


#: what the ros2 service publishes in each robot's namespace (``/<robot>/pose``...: ``twohr_services.ros2``'s
#: default topics), which every robot may read of the others
ROS2_SHARED_TOPICS = ("pose", "odom", "path", "path_corrected", "tf")
#: global topics every robot may read (the transforms), and those every stock ROS 2 node publishes to
ROS2_READ_GLOBAL, ROS2_WRITE_GLOBAL = ("tf", "tf_static"), ("rosout", "parameter_events")


def _topic(domain: int, topic: str) -> str:
    # one topic exactly: rmw_zenoh's data key is <domain>/<topic>/<type>/<hash>
    return f"{domain}/{topic}/*/*"


def robot_ros2_grants(robot: str, domain: int = 0) -> Grants:
    """Robot ``robot``'s ROS 2 keys: it reads and writes its own namespace (``/<robot>/...``, services included),
    publishes ``/rosout`` and ``/parameter_events`` (stock nodes do), and reads the other robots' poses, odometry,
    paths and transforms and the global ``/tf`` and ``/tf_static``, nothing else of theirs; the stack's global
    topics (``/tf``, ``/clock``, ``/diagnostics``...) it may not publish. Its liveliness tokens (rmw_zenoh's
    ``@ros2_lv/<domain>/<zid>/<nid>/<eid>/<kind>/<enclave>/<namespace>/<node>/...``, ``/`` in names as ``%``) name
    nodes of its namespace only, and their endpoints only topics it may use; it watches the whole graph."""
    own = f"{domain}/{robot}/**"
    writes = [_topic(domain, topic) for topic in ROS2_WRITE_GLOBAL]
    reads = [_topic(domain, f"*/{topic}") for topic in ROS2_SHARED_TOPICS] + [
        _topic(domain, topic) for topic in ROS2_READ_GLOBAL]
    lv = f"{ADMIN_SPACE_ROS2}/{domain}/*/*/*"
    mine = f"%{robot}%$*"  # a topic or service under /<robot>/
    endpoints = {"MP": [mine, *(f"%{t}" for t in ROS2_WRITE_GLOBAL)], "SS": [mine], "SC": [mine],
                 "MS": [mine, *(f"%$*%{t}" for t in ROS2_SHARED_TOPICS), *(f"%{t}" for t in ROS2_READ_GLOBAL)]}
    tokens = []
    for namespace in (f"%{robot}", mine):  # nodes of the robot's namespace, or of one under it
        tokens.append(f"{lv}/NN/*/{namespace}/*")
        tokens += [f"{lv}/{kind}/*/{namespace}/*/{topic}/**" for kind, topics in endpoints.items() for topic in topics]
    return Grants(publish=[own, *writes], subscribe=[own, *reads, f"{ADMIN_SPACE_ROS2}/{domain}/**"], serve=[own],
                  ask=[own], tokens=tokens)


def role_grants(ros2_domain: int = 0) -> dict[str, Grants]:
    """Every role's grants; ROS 2 keys are granted in ``ros2_domain`` only."""
    ros2 = ros2_keys(ros2_domain)
    # what twohr hands to the outside: camera drivers, other robots, viewers, ROS 2 nodes, `twohr health`
    client = Grants(publish=_robots("camera") + ros2,
                    subscribe=_robots("pose", "path", "status", "landmarks") + [merged_key()] + ros2,
                    ask=[f"{MAPS_PREFIX}/*"], watch_liveliness=True)
    return {
        # every stream: the session table follows poses and statuses, the live view shows the rest
        "gateway": Grants(publish=_robots("control"), subscribe=[f"{PREFIX}/*/*", merged_key()],
                          watch_liveliness=True),
        "source": Grants(publish=_robots("frames", "status"),
                         subscribe=_robots("control", "pose", "status", "camera")),
        # the networks answer the tracker's queries only (each answer is published for recordings and views)
        "detector": Grants(publish=_robots("keypoints", "status"), subscribe=_robots("control"),
                           serve=_robots("rpc/detect/*")),
        "yolo": Grants(publish=_robots("dynamics", "status"), subscribe=_robots("control"),
                       serve=_robots("rpc/dynamics/*")),
        "matcher": Grants(publish=_robots("matches", "status"), subscribe=_robots("control"),
                          serve=_robots("rpc/match/*")),
        "tracker": Grants(publish=_robots("pose", "path", "status", "landmarks", "keyframes") + [snapshot_key()],
                          subscribe=_robots("control", "frames", "pose") + [merged_key()],
                          # each keyframe job to one replica of a network service, followed by its liveliness
                          ask=_robots("rpc/detect/*", "rpc/dynamics/*", "rpc/match/*") + [
                              f"{MAPS_PREFIX}/*", f"{MAPS_PREFIX}/*/save", snapshot_key()], watch_liveliness=True),
        # the map room: the map store and the sessions' map snapshots served; the robots' keyframes in, the merges
        # of the shared maps out
        "mapserver": Grants(publish=_robots("status") + [merged_key()],
                            subscribe=_robots("control", "keyframes") + [snapshot_key()],
                            serve=[f"{MAPS_PREFIX}/*", f"{MAPS_PREFIX}/*/save", snapshot_key()]),
        "recorder": Grants(publish=_robots("status"), subscribe=[f"{PREFIX}/*/*", merged_key()]),
        "ros2": Grants(publish=_robots("camera") + ros2,
                       subscribe=_robots("pose", "path", "status", "landmarks") + [merged_key()] + ros2),
        "client": client,
        # a robot's own router linked to this one: it forwards what its clients may do, no more
        "router": client,
    }


def uplink_grants(ros2_domain: int = 0) -> Grants:
    """What the stack's router may do on a robot's own router that links to it (the mirror of a client): send
    the results its clients read, receive the cameras they publish, answer health queries."""
    client = role_grants(ros2_domain)["client"]
    return Grants(publish=client.subscribe, subscribe=client.publish, serve=[f"{HEALTH_PREFIX}/**"])


def _rule(rule_id: str, messages: list[str], flow: str, key_exprs: list[str]) -> dict:
    return {"id": rule_id, "messages": messages, "flows": [flow], "permission": "allow", "key_exprs": key_exprs}


def role_rules(role: str, grants: Grants) -> list[dict]:
    """The ACL rules of one role. ``ingress`` is what the role sends to the router, ``egress`` what the router
    sends to it: a publisher sends puts and learns of matching subscribers; a subscriber declares interest and
    receives puts; a queryable declares itself, receives queries and sends replies; a querier the reverse."""
    rules = []
    own = [f"{HEALTH_PREFIX}/{role}/*"]  # each replica answers on its own key
    serve = grants.serve + own
    if grants.publish:
        rules += [_rule(f"{role}-pub", ["put", "delete"], "ingress", grants.publish),
                  _rule(f"{role}-pub-match", ["declare_subscriber"], "egress",
                        grants.publish if grants.matching is None else grants.matching)]
    if grants.subscribe:
        rules += [_rule(f"{role}-sub", ["declare_subscriber"], "ingress", grants.subscribe),
                  _rule(f"{role}-sub-data", ["put", "delete"], "egress", grants.subscribe)]
    ask = grants.ask + ([f"{HEALTH_PREFIX}/**"] if grants.read_health else [])
    rules += [_rule(f"{role}-serve", ["declare_queryable", "reply"], "ingress", serve),
              _rule(f"{role}-serve-query", ["query"], "egress", serve),
              _rule(f"{role}-alive", ["liveliness_token"], "ingress", [f"{ALIVE_PREFIX}/{role}/*"])]
    if ask:
        rules += [_rule(f"{role}-ask", ["query"], "ingress", ask),
                  _rule(f"{role}-ask-reply", ["reply", "declare_queryable"], "egress", ask)]
    ros2_tokens = grants.tokens + [k for k in grants.publish if k.startswith(f"{ADMIN_SPACE_ROS2}/")]
    if ros2_tokens:
        rules.append(_rule(f"{role}-ros2-tokens", ["liveliness_token"], "ingress", ros2_tokens))
    watched = ([f"{ALIVE_PREFIX}/**"] if grants.watch_liveliness else grants.watch) + [
        k for k in grants.subscribe if k.startswith(f"{ADMIN_SPACE_ROS2}/")]
    if watched:
        rules += [_rule(f"{role}-watch", ["declare_liveliness_subscriber", "liveliness_query"], "ingress", watched),
                  _rule(f"{role}-watch-tokens", ["liveliness_token", "reply"], "egress", watched)]
    return rules


#: what a robot's own tracker publishes of its robot, as the stack's tracker does
TRACKER_RESULTS = ("pose", "path", "status", "landmarks", "keyframes")


def robot_grants(robot: str, ros2_domain: int = 0, edge: bool = False) -> Grants:
    """What robot ``robot`` may do on a fleet's bus: what a ``client`` may of twohr's keys, but publish only its own
    camera, read only its own live map points (``landmarks``), and neither ask the services' health nor follow their
    liveliness tokens (both name every replica and its host: the operator's, through ``GET /healthz``); of ROS 2,
    :func:`robot_ros2_grants`.

    ``edge`` (``twohr keys add --edge``): it runs its own tracker (``twohr camera --edge``), which also publishes
    the robot's own results (:data:`TRACKER_RESULTS`), hears its own sessions start and stop, asks the network
    services' replicas for its own keyframes (following their tokens: these name the replicas' hosts), fetches maps
    (saving one stays the stack's tracker's), and holds the token and answers the health query of tracker
    ``edge+<robot>``; of any other robot's keys, nothing more."""
    client = role_grants(ros2_domain)["client"]
    ros2 = robot_ros2_grants(robot, ros2_domain)
    # another robot's live map points are not its to read (the live view hides them too): its own only
    others_points = _robots("landmarks")
    twohr_only = [k for k in client.subscribe if k.startswith(f"{PREFIX}/") and k not in others_points] + [
        key(robot, "landmarks")]
    grants = Grants(publish=[key(robot, RAW_CAMERA), *ros2.publish], subscribe=twohr_only + ros2.subscribe,
                    serve=ros2.serve, ask=client.ask + ros2.ask, watch_liveliness=False, read_health=False,
                    matching=[k for k in client.publish if k.startswith(f"{PREFIX}/")] + ros2.publish,
                    tokens=ros2.tokens)
    if edge:
        replica = edge_replica(robot)
        grants.publish += [key(robot, stream) for stream in TRACKER_RESULTS]
        grants.subscribe.append(key(robot, CONTROL))
        # no map saves: the map store takes a save without a session as the operator's (a robot's own tracker
        # localizes in stored maps; building or extending one runs on the stack)
        grants.ask += [f"{key(robot, query)}/*" for query in (DETECT_QUERY, DYNAMICS_QUERY, MATCH_QUERY)]
        grants.serve.append(health_key("tracker", replica))
        grants.tokens.append(alive_key("tracker", replica))
        grants.watch += [alive_key(service) for service in NETWORK_SERVICES]
        grants.matching += [key(robot, stream) for stream in TRACKER_RESULTS]
    return grants


def _policy(subjects: list[dict], rules: list[dict]) -> tuple[list[dict], list[dict], dict]:
    """``rules`` and one policy that gives them to every one of ``subjects`` (the policy is named for the first)."""
    return rules, subjects, {"id": f"{subjects[0]['id']}-policy", "rules": [r["id"] for r in rules],
                             "subjects": [subject["id"] for subject in subjects]}


def access_control(ros2_domain: int = 0, uplinks: list[str] | None = None, robots: list[str] | None = None,
                   replicas: list[str] | None = None, edge: list[str] | None = None) -> dict:
    """The router's ``access_control`` section: deny by default, allow what :func:`role_grants` lists.

    Without ``robots``, each role is known by its user name, and every outside client shares the ``client`` role.
    With ``robots`` (a fleet's stack), each service role and each robot is known by its certificate's common name
    and its user name together, and robot ``r`` gets :func:`robot_grants` (those of ``edge`` with their own tracker's
    rights); there is no shared ``client`` or
    ``router`` role; each of ``replicas`` (``ROLE@HOST``, a service replica of another host with a certificate of its
    own) is known by that name and gets its role's rules. A robot's own router that links to the stack's router
    lists that router's Zenoh ids as ``uplinks`` and grants it :func:`uplink_grants`: the router that dials is the
    one that authenticates, so the router dialled is known here by its id alone."""
    parts = []
    for role, grants in role_grants(ros2_domain).items():
        if robots is None:
            parts.append(_policy([{"id": role, "usernames": [role]}], role_rules(role, grants)))
        elif role not in ("client", "router"):
            names = [role, *(name for name in replicas or [] if name.partition("@")[0] == role)]
            parts.append(_policy([{"id": name, "cert_common_names": [name], "usernames": [name]} for name in names],
                                 role_rules(role, grants)))
    for robot in robots or []:
        subject = {"id": f"robot-{robot}", "cert_common_names": [robot], "usernames": [robot]}
        grants = robot_grants(robot, ros2_domain, edge=robot in (edge or []))
        parts.append(_policy([subject], role_rules(subject["id"], grants)))
    if uplinks:
        parts.append(_policy([{"id": "uplink", "zids": list(uplinks)}],
                             role_rules("uplink", uplink_grants(ros2_domain))))
    return {"enabled": True, "default_permission": "deny", "rules": [r for rules, _, _ in parts for r in rules],
            "subjects": [subject for _, subjects, _ in parts for subject in subjects],
            "policies": [policy for _, _, policy in parts]}


def is_loopback(endpoint: str) -> bool:
    """Whether a Zenoh endpoint (``tcp/HOST:PORT``) or a bare host is reachable from this host only (a loopback
    address or ``localhost``; :func:`twohr.bus.is_loopback_host`)."""
    return is_loopback_host(endpoint_host(endpoint))
