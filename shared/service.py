"""The thin shell every service shares: subscribe, queue, call the core, publish.

A :class:`Service` subscribes to key expressions, puts each sample into a bounded
:class:`Inbox` (policy ``drop_oldest`` or ``backpressure``), and one worker thread hands the
samples to :meth:`Service.handle`. A malformed payload is counted and logged, never fatal.
Each service process is one *replica* of its service (:func:`replica_id`): it answers a
health query on ``twohr/_health/<name>/<replica>`` with its counters, and holds a liveliness token
``twohr/_alive/<name>/<replica>`` while it is connected, so that the gateway notices at once when the last
replica of a service dies, and the tracker sends keyframe jobs only to replicas that are alive
(:mod:`twohr.replicas`).

Per-session state exists only for sessions whose ``start`` control message this service saw: a message
for any other session is counted as ``ignored`` and dropped, and a message whose header names another
robot than its key is ``malformed``. A ``start`` this service cannot honour (a config its core rejects)
is answered with an ``error`` status on ``twohr/<robot>/status``, which fails the session at once.
"""

from __future__ import annotations

import collections
import functools
import json
import logging
import os
import re
import secrets
import signal
import socket
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Literal

import zenoh

from . import keys
from .bus import BusConfig, add_router_option, bus_from_args, open_session
from .config import PipelineConfig
from .errors import TwohrError
from .messages import ControlMsg, MessageError, StatusMsg, decode, encode, split

QueuePolicy = Literal["drop_oldest", "backpressure"]
#: distinct model configs a service keeps loaded at once (each holds a network); the least recently used goes
MODEL_CACHE_SIZE = 3
#: CPU priority of a service run as a program, by what it does (``Service.priority``; niceness, lower = first):
#: * ``per_frame`` (the tracker): raised by :data:`PER_FRAME_NICE` (``TWOHR_PER_FRAME_NICE``) where the process may
#:   (root, or the capability CAP_SYS_NICE), so that a frame's pose goes first on a robot's busy CPU;
#: * ``keyframe`` (detector, yolo, matcher): normal priority. The map's work takes the same share of the CPU as any
#:   other process of the robot, never less: at a lower priority, one busy process beside the stack starved the
#:   keyframe jobs and made a live trajectory six times worse;
#: * ``background`` (the recorder): lowered by :data:`BACKGROUND_NICE` (``TWOHR_BACKGROUND_NICE``): a recording may
#:   lag, nothing waits for it.
PER_FRAME_NICE = -5
BACKGROUND_NICE = 10
ServicePriority = Literal["per_frame", "keyframe", "normal", "background"]
COUNTERS = ("received", "processed", "dropped", "malformed", "ignored", "errors")
#: queries of one robot a service holds waiting at most (a tracker has a few keyframe jobs in flight per robot)
MAX_QUEUED_QUERIES = 64
#: sessions whose robot a service remembers (a start past this forgets the oldest)
SESSIONS_REMEMBERED = 1024


def robot_of(key: str) -> str:
    """The robot of a per-robot key (``twohr/<robot>/...``), '' for any other key: whose queue an item joins."""
    return key.split("/", 2)[1] if key.count("/") >= 2 else ""


class UnknownSession(Exception):
    """A message for a session whose start this service never saw (or that has ended)."""


@dataclass
class Counters:
    """What a service has seen; read by the health query and the tests."""

    received: int = 0
    processed: int = 0
    dropped: int = 0
    malformed: int = 0
    ignored: int = 0
    errors: int = 0
    lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def add(self, name: str, n: int = 1) -> None:
        with self.lock:
            setattr(self, name, getattr(self, name) + n)

    def as_dict(self) -> dict[str, int]:
        with self.lock:
            return {k: getattr(self, k) for k in COUNTERS}


class Inbox:
    """A bounded FIFO. ``drop_oldest`` discards the oldest item when full (fresh data wins, for live
    cameras); ``backpressure`` blocks the producer until there is room (nothing lost, for playback).

    ``fair``: one FIFO per robot (the robot of the item's key, ``twohr/<robot>/...``), served in turn, so that on
    an overloaded stack every robot's samples get the same number of turns, whatever their order of arrival."""

    def __init__(self, maxsize: int, policy: QueuePolicy, counters: Counters, fair: bool = False) -> None:
        self.items: collections.deque | _RobotQueues = _RobotQueues() if fair else collections.deque()
        self.urgent: collections.deque = collections.deque()  # control messages and queries
        self.maxsize = maxsize
        self.policy = policy
        self.counters = counters
        self.cond = threading.Condition()

    def put(self, item, urgent: bool = False) -> None:
        """Queue ``item``; ``urgent`` items (control messages, queries) are never dropped and go first."""
        with self.cond:
            if urgent:
                self.urgent.append(item)
            elif self.policy == "backpressure":
                while len(self.items) >= self.maxsize:
                    self.cond.wait(0.1)
            elif len(self.items) >= self.maxsize:
                self.items.popleft()
                self.counters.add("dropped")
            if not urgent:
                self.items.append(item)
            self.cond.notify_all()

    def get(self, timeout: float):
        with self.cond:
            if not self.items and not self.urgent:
                self.cond.wait(timeout)
            if self.urgent:
                return self.urgent.popleft()
            if not self.items:
                return None
            item = self.items.popleft()
            self.cond.notify_all()
            return item

    def __len__(self) -> int:
        return len(self.items) + len(self.urgent)


class _RobotQueues:
    """The deque operations :class:`Inbox` uses, over one FIFO per robot: ``popleft`` takes the oldest item of the
    robot whose turn it is, turns going round the robots with items waiting."""

    def __init__(self) -> None:
        self.queues: collections.OrderedDict[str, collections.deque] = collections.OrderedDict()
        self.size = 0

    def append(self, item) -> None:
        robot = robot_of(str(item[0]))
        self.queues.setdefault(robot, collections.deque()).append(item)
        self.size += 1

    def popleft(self):
        if not self.size:
            raise IndexError("pop from an empty inbox")
        robot, queue = next(iter(self.queues.items()))
        item = queue.popleft()
        del self.queues[robot]
        if queue:
            self.queues[robot] = queue  # the robot's next item waits for the others' turns
        self.size -= 1
        return item

    def __len__(self) -> int:
        return self.size


class Service:
    """Base class of the service adapters. Subclasses set ``name``, list ``subscriptions()`` and
    implement ``handle(key, payload)``; they publish with ``self.publish(key, payload)``."""

    name = "service"
    #: subscribe to control messages and keep ``session_configs`` (the pipeline stages do)
    follows_sessions = False
    #: a session moved to this replica (``ControlMsg`` ``move``: its own died) is started here again, with
    #: ``on_session_start``; other services go on with it as they were
    follows_moves = False
    #: the CPU priority it takes when run as a program (see :data:`PER_FRAME_NICE`)
    priority: ServicePriority = "normal"

    def __init__(self, bus: BusConfig | None = None, queue_size: int = 8, policy: QueuePolicy = "backpressure",
                 fair: bool = False) -> None:
        self.bus = bus or BusConfig()
        self.counters = Counters()
        self.inbox = Inbox(queue_size, policy, self.counters, fair=fair)
        self.log = logging.getLogger(f"twohr.{self.name}")
        self.session: zenoh.Session | None = None
        self.stopping = threading.Event()
        self._publishers: dict[str, zenoh.Publisher] = {}
        self.session_configs: dict[str, PipelineConfig] = {}
        self.session_robots: dict[str, str] = {}  # session -> the robot its start control named
        self._queued_queries: dict[str, int] = {}  # robot -> its queries waiting in the inbox
        self.refused: dict[str, int] = {}  # robot (of the key) -> messages refused (malformed, or not its session's)
        self.replica = replica_id()

    # -- to override
    def subscriptions(self) -> list[str]:
        return []

    def control_keys(self) -> list[str]:
        """Where it hears sessions start and stop (when it ``follows_sessions``): every robot's control key."""
        return [keys.all_robots(keys.CONTROL)]

    def on_session_start(self, control: ControlMsg) -> None:
        """A session starts: set up per-session state (its config is ``control.config``)."""

    def on_session_stop(self, session_id: str) -> None:
        """A session ends: drop its per-session state."""

    def handle(self, key: str, payload: bytes) -> None:
        raise NotImplementedError

    def on_start(self) -> None:
        """Called once the bus session is open (declare queryables here)."""

    def warm_up(self, what: str, work) -> None:
        """Run ``work()`` once (load and run the default model) before this service declares itself alive, so
        that the first session's first keyframe does not wait for it. A failure (a missing model, say) is only
        logged: the session that needs the model reports it."""
        t0 = time.perf_counter()
        try:
            work()
        except Exception as exc:
            self.log.warning("could not warm up %s: %s", what, exc)
            return
        self.log.info("%s warm in %.2f s", what, time.perf_counter() - t0)

    def health(self) -> dict:
        with self.counters.lock:
            refused = dict(self.refused)
        return {"service": self.name, "replica": self.replica, "host": socket.gethostname(), "pid": os.getpid(),
                "queue": len(self.inbox), **self.counters.as_dict(), "refused": refused}

    def declare_replica_queryable(self, query: str) -> zenoh.Queryable:
        """Answer ``query`` (e.g. ``rpc/detect``) for every robot, as this replica: the tracker picks one replica
        per job and asks it on ``twohr/<robot>/<query>/<replica>``."""
        return self.session.declare_queryable(f"{keys.all_robots(query)}/{self.replica}", self._on_query)

    # -- the shell
    def publish(self, key: str, payload: bytes) -> None:
        if key not in self._publishers:
            self._publishers[key] = declare_publisher(self.session, key)
        self._publishers[key].put(payload)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        self.counters.add("received")
        key = str(sample.key_expr)
        self.inbox.put((key, sample.payload.to_bytes()), urgent=key.endswith("/" + keys.CONTROL))

    def _on_query(self, query: zenoh.Query) -> None:
        """Queue a query (a request/reply stage); it is served before any queued stream sample. A robot with
        :data:`MAX_QUEUED_QUERIES` queries waiting already is answered "busy" at once: one robot's flood of
        queries holds no other robot's up, and the queue stays bounded."""
        self.counters.add("received")
        key = str(query.key_expr)
        robot = robot_of(key)
        with self.counters.lock:
            waiting = self._queued_queries.get(robot, 0)
            if waiting < MAX_QUEUED_QUERIES:
                self._queued_queries[robot] = waiting + 1
        if waiting >= MAX_QUEUED_QUERIES:
            self.counters.add("dropped")
            query.reply_err(f"{self.name}: busy: robot {robot} has {waiting} queries waiting here".encode())
            query.drop()
            return
        self.inbox.put((key, query), urgent=True)

    def _dequeued_query(self, key: str) -> None:
        robot = robot_of(key)
        with self.counters.lock:
            left = self._queued_queries.get(robot, 1) - 1
            if left > 0:
                self._queued_queries[robot] = left
            else:
                self._queued_queries.pop(robot, None)

    def config_for(self, session_id: str) -> PipelineConfig:
        """The pipeline config of a running session; raises :class:`UnknownSession` for any other."""
        config = self.session_configs.get(session_id)
        if config is None:
            raise UnknownSession(session_id)
        return config

    def takes(self, control: ControlMsg) -> bool:
        """Whether this replica serves the session ``control`` starts or stops (every one does, unless a service
        serves only the sessions assigned to it)."""
        return True

    def _check_owner(self, header) -> None:
        """:class:`MessageError` for a message on a session another robot started: a session id is no secret (every
        robot may read another's poses), its start control says whose it is."""
        owner = self.session_robots.get(header.session_id)
        if owner is not None and owner != header.robot_id:
            raise MessageError(f"robot {header.robot_id!r} spoke for session {header.session_id}, which is robot "
                               f"{owner!r}'s")

    def _handle_control(self, payload: bytes) -> None:
        control, _ = decode(payload, ControlMsg)
        if control.command in ("start", "move"):  # an ended session's too: its last messages come after its stop
            self.session_robots[control.session_id] = control.robot_id
            while len(self.session_robots) > SESSIONS_REMEMBERED:
                self.session_robots.pop(next(iter(self.session_robots)))
        if not self.takes(control):
            return
        if control.command == "move" and not self.follows_moves:
            return
        if control.command in ("start", "move"):
            try:
                self.on_session_start(control)
            except Exception as exc:
                self.on_session_stop(control.session_id)
                self.report(control, "error", f"{self.name}: {exc}")
                raise
            self.session_configs[control.session_id] = control.config
        else:
            self.on_session_stop(control.session_id)
            self.session_configs.pop(control.session_id, None)

    def report(self, about, state: str, detail: str = "", **counters: int) -> None:
        """Publish a session status (``about`` is any message of that session) on ``twohr/<robot>/status``."""
        status = StatusMsg(session_id=about.session_id, robot_id=about.robot_id, frame_index=-1, stamp=time.time(),
                           service=self.name, state=state, detail=detail[:2000], counters=counters)
        self.publish(keys.key(about.robot_id, "status"), encode(status))

    def _on_health(self, query: zenoh.Query) -> None:
        query.reply(keys.health_key(self.name, self.replica), json.dumps(self.health()))

    def process_one(self, timeout: float = 0.2) -> bool:
        """Handle one queued sample; False if none arrived within ``timeout``."""
        item = self.inbox.get(timeout)
        if item is None:
            return False
        key, payload = item
        if isinstance(payload, zenoh.Query):
            self._dequeued_query(key)
        try:
            header = check_robot(key, payload)
            if header is not None and self.follows_sessions and not key.endswith("/" + keys.CONTROL):
                self._check_owner(header)
        except MessageError as exc:
            self._refuse(key, payload, exc)
            return True
        try:
            if self.follows_sessions and key.endswith("/" + keys.CONTROL):
                self._handle_control(payload)
            else:
                self.handle(key, payload)
            self.counters.add("processed")
        except MessageError as exc:
            self._refuse(key, payload, exc, answer=False)  # a query's handler answers it (reply_to)
        except UnknownSession as exc:
            self.counters.add("ignored")
            if isinstance(payload, zenoh.Query):
                payload.reply_err(f"{self.name}: no running session {exc}".encode())
            self.log.debug("ignored a message on %s for session %s, which this service does not run", key, exc)
        except Exception:  # a bad frame must not take the service down
            self.counters.add("errors")
            self.log.exception("error while handling %s", key)
        return True

    def _refuse(self, key: str, payload, exc: MessageError, answer: bool = True) -> None:
        """A message refused: counted (in all and by the robot of its key), said, and (``answer``) a query answered
        at once."""
        self.counters.add("malformed")
        robot = robot_of(key)
        with self.counters.lock:
            self.refused[robot] = self.refused.get(robot, 0) + 1
        self.log.warning("refused a message on %s: %s", key, exc)
        if answer and isinstance(payload, zenoh.Query):
            payload.reply_err(f"{self.name}: {exc}".encode())

    def run(self, stop: threading.Event | None = None) -> None:
        """Serve until ``stop`` is set (or SIGINT/SIGTERM when run as a program)."""
        stop = stop or self.stopping
        self.session = open_session(self.bus)
        wanted = self.subscriptions() + (self.control_keys() if self.follows_sessions else [])
        subscribers = [self.session.declare_subscriber(k, self._on_sample) for k in wanted]
        self.on_start()  # queryables, and warm models: healthy and alive means ready
        queryable = self.session.declare_queryable(keys.health_key(self.name, self.replica), self._on_health)
        alive = self.session.liveliness().declare_token(keys.alive_key(self.name, self.replica))
        self.log.info("%s serving %s", self.name, ", ".join(self.subscriptions()) or "(no subscriptions)")
        try:
            while not stop.is_set():
                self.process_one()
        finally:
            alive.undeclare()
            for sub in subscribers:
                sub.undeclare()
            queryable.undeclare()
            self.session.close()

    def take_priority(self) -> None:
        """Set this process's CPU priority for its :attr:`priority` (see :data:`PER_FRAME_NICE`)."""
        if self.priority == "per_frame":
            nice = nice_from_env("TWOHR_PER_FRAME_NICE", PER_FRAME_NICE, self.log)
            if not change_priority(nice):
                self.log.info("running at normal priority: raising it by %d needs root or CAP_SYS_NICE", -nice)
        elif self.priority == "background":
            change_priority(nice_from_env("TWOHR_BACKGROUND_NICE", BACKGROUND_NICE, self.log))

    def run_forever(self) -> None:
        """Entry point for ``python -m``: stop cleanly on SIGINT and SIGTERM."""
        logging.basicConfig(level=os.environ.get("TWOHR_LOG_LEVEL", "INFO"),
                            format="%(asctime)s %(levelname)s %(name)s: %(message)s")
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: self.stopping.set())
        self.take_priority()
        self.run(self.stopping)
        # the bus session is closed and every session finished: leave now. A replica found after a stack's stop had
        # hung in the interpreter's exit (one thread left, waiting on a lock of Zenoh's runtime, SIGTERM caught and
        # ignored), and with its supervisor gone no one sends the SIGKILL that ends such a process
        logging.shutdown()
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0)


def replica_id() -> str:
    """This process's replica name: ``TWOHR_REPLICA``, else ``<host>-<pid>-<4 random hex>`` (containers on the
    host's network share its name and may all be pid 1); one key chunk: letters, digits, ``.``, ``_``, ``-``."""
    name = os.environ.get("TWOHR_REPLICA") or f"{socket.gethostname()}-{os.getpid()}-{secrets.token_hex(2)}"
    return re.sub(r"[^A-Za-z0-9._-]", "-", name)[:96] or f"replica-{os.getpid()}"


def nice_from_env(name: str, default: int, log: logging.Logger) -> int:
    """A niceness change from the environment variable ``name`` (a whole number, may be negative), else ``default``;
    a value that is no whole number is one warning."""
    value = os.environ.get(name, str(default)).strip()
    try:
        return int(value)
    except ValueError:
        log.warning("%s=%r is not a whole number; using %d", name, value, default)
        return default


def change_priority(nice: int) -> bool:
    """Change this process's niceness by ``nice`` (negative: higher priority), for every thread it has (Linux keeps
    niceness per thread; threads started later inherit it). Lowering needs no privileges; raising needs root or
    CAP_SYS_NICE, and returns False where it is not allowed (nothing changes then)."""
    if nice == 0:
        return True
    task_dir = "/proc/self/task"
    threads = [int(t) for t in os.listdir(task_dir)] if os.path.isdir(task_dir) else [0]
    for thread in threads:
        try:
            current = os.getpriority(os.PRIO_PROCESS, thread)
            os.setpriority(os.PRIO_PROCESS, thread, max(-20, min(19, current + nice)))
        except PermissionError:
            return False
        except OSError:
            pass  # a thread that has just ended
    return True


def check_robot(key: str, payload):
    """Raise :class:`MessageError` unless a twohr message's header names the robot of the key it came on: a
    publisher allowed on ``twohr/r2/...`` must not speak for ``r1``. Returns the header (None for a key of no
    robot's)."""
    if isinstance(payload, zenoh.Query):
        payload = payload.payload.to_bytes() if payload.payload is not None else b""
    try:
        robot, _ = keys.parse(key)
    except ValueError:
        return None  # not a per-robot key (health, liveliness)
    if robot in keys.RESERVED_ROBOT_IDS:
        return None  # a map's key (twohr/maps/<name>/...): its messages are about any robot of the map
    message, _ = split(payload)
    if message.robot_id != robot:
        raise MessageError(f"a message for robot {message.robot_id!r} on {key}")
    return message


def reply_to(query: zenoh.Query, answer) -> None:
    """Answer a query with ``answer(payload) -> bytes``; anything that goes wrong is replied as an error at
    once (the caller must not wait out its timeout) and then raised for the service's counters."""
    payload = query.payload.to_bytes() if query.payload is not None else b""
    try:
        data = answer(payload)
    except Exception as exc:
        query.reply_err(f"{type(exc).__name__}: {exc}"[:500].encode())
        raise
    query.reply(query.key_expr, data)


def declare_publisher(session: zenoh.Session, key: str, wait_for_subscribers: float = 2.0) -> zenoh.Publisher:
    """A reliable, blocking publisher; waits up to ``wait_for_subscribers`` s until the bus reports a matching
    subscriber, so that the first messages on a new key are not dropped while routes are still being set up."""
    publisher = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
    deadline = time.monotonic() + wait_for_subscribers
    while not publisher.matching_status.matching and time.monotonic() < deadline:
        time.sleep(0.02)
    return publisher


def one_line_errors(name: str):
    """Decorate a service's ``main``: a :class:`~twohr.errors.TwohrError` (an unusable key folder, a bus that will
    not have it, a bad flag value) ends the process with exit code 2 and one line, not a traceback."""
    def wrap(main):
        @functools.wraps(main)
        def run(*args, **kwargs):
            try:
                return main(*args, **kwargs)
            except TwohrError as exc:
                print(f"{name}: error: {exc}", file=sys.stderr, flush=True)
                raise SystemExit(2) from None
        return run
    return wrap


def service_parser(name: str, description: str | None = None):
    """The command line of ``python -m twohr_services.<name>``, with the options every service takes (``--router``);
    a service adds its own."""
    import argparse


    parser = argparse.ArgumentParser(prog=f"python -m twohr_services.{name}", description=description,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    add_router_option(parser)
    return parser


def serve(service_cls: type[Service], argv: list[str] | None = None, **kwargs) -> None:
    """``python -m twohr_services.<name>``: parse the common options and run the service until SIGINT/SIGTERM."""
    @one_line_errors(service_cls.name)
    def main() -> None:
        args = service_parser(service_cls.name, (service_cls.__doc__ or "").strip()).parse_args(argv)
        service_cls(bus_from_args(args), **kwargs).run_forever()

    main()
