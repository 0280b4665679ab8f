"""Replicas of a network service as the tracker uses them (:class:`twohr.replicas.Replicas`): a real router, and
each replica a real process with its own Zenoh session, its liveliness token and its queryable, as a service's.
Each job goes to exactly one replica, the least busy; a job whose replica is killed while it works is answered by
another; a replica that comes back is used again."""

from __future__ import annotations

import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor

import pytest

from twohr.bus import BusConfig, free_port, open_session, start_router
from twohr.replicas import NoReplica, Replicas

SERVICE, QUERY = "echo", "rpc/echo"
#: a replica: its token, and a queryable that answers ``<replica name> <count>`` after ``delay`` s, each job one
#: line on stdout
REPLICA = """
import sys, threading, time
from twohr import keys
from twohr.bus import BusConfig, open_session
router, name, delay = sys.argv[1], sys.argv[2], float(sys.argv[3])
session = open_session(BusConfig(connect=[router], config_file=None))
count = 0
lock = threading.Lock()
def answer(query):
    global count
    with lock:
        count += 1
        n = count
    print("job", n, flush=True)
    time.sleep(delay)
    query.reply(query.key_expr, f"{name} {n}".encode())
queryable = session.declare_queryable(f"{keys.all_robots('rpc/echo')}/{name}", answer)
token = session.liveliness().declare_token(keys.alive_key("echo", name))
print("ready", flush=True)
threading.Event().wait()
"""


class Replica:
    def __init__(self, router: str, name: str, delay: float) -> None:
        self.proc = subprocess.Popen([sys.executable, "-c", REPLICA, router, name, str(delay)], text=True,
                                     stdout=subprocess.PIPE)
        assert self.proc.stdout.readline().strip() == "ready"

    def jobs(self) -> int:
        """Jobs it took, once it has been stopped."""
        self.kill()
        return sum(line.startswith("job") for line in self.proc.stdout.read().splitlines())

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait()


@pytest.fixture
def bus():
    """(a replica starter, the caller's session) on a router of its own; every replica is killed at the end."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = start_router([endpoint])
    caller = open_session(BusConfig(connect=[endpoint], config_file=None))
    started: list[Replica] = []

    def replica(name: str, delay: float) -> Replica:
        started.append(Replica(endpoint, name, delay))
        return started[-1]

    yield replica, caller
    for one in started:
        one.kill()
    caller.close()
    router.close()


def wait_alive(replicas: Replicas, names: list[str], timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while replicas.alive() != sorted(names):
        assert time.monotonic() < deadline, replicas.alive()
        time.sleep(0.05)


def test_each_job_goes_to_one_replica_and_the_least_busy_takes_the_next(bus):
    replica, caller = bus
    a, b = replica("a", 0.5), replica("b", 0.5)
    replicas = Replicas(caller, SERVICE)
    wait_alive(replicas, ["a", "b"])
    with ThreadPoolExecutor(6) as pool:
        answers = list(pool.map(lambda i: replicas.call("r1", QUERY, b"job").decode().split()[0], range(6)))
    assert sorted(answers) == ["a"] * 3 + ["b"] * 3  # three in flight on each at once
    assert (a.jobs(), b.jobs()) == (3, 3)  # each job to one replica, never two
    answered = {"a": 3, "b": 3}
    assert replicas.stats() | {"alive": [], "bytes_received": 0} == {
        "alive": [], "answered": answered, "retried": 0, "lost": 0, "bytes_sent": 6 * len(b"job"), "bytes_received": 0}
    assert replicas.stats()["bytes_received"] > 0  # the answers name their replica


def test_a_job_whose_replica_is_killed_is_answered_by_another_and_the_replica_rejoins(bus):
    replica, caller = bus
    slow = replica("a", 5.0)
    replica("b", 0.0)
    replicas = Replicas(caller, SERVICE)
    wait_alive(replicas, ["a", "b"])
    with ThreadPoolExecutor(1) as pool:
        job = pool.submit(replicas.call, "r1", QUERY, b"job")  # to a: both idle, none served, a first by name
        time.sleep(1.0)
        slow.kill()  # kill -9 while a works on the job
        t0 = time.monotonic()
        assert job.result(timeout=10).decode() == "b 1"
    failover_s = time.monotonic() - t0
    print(f"the job in flight on the killed replica was answered by the other {failover_s:.3f} s after the kill")
    assert failover_s < 3.0, "the job waited for its timeout instead of going on at once"
    assert replicas.stats()["retried"] == 1 and replicas.stats()["lost"] == 0
    wait_alive(replicas, ["b"])
    replica("a", 0.0)  # the same replica comes back: it is used again, nothing restarted
    wait_alive(replicas, ["a", "b"])
    answers = [replicas.call("r1", QUERY, b"job").decode().split()[0] for _ in range(4)]
    # one at a time, each goes to the replica that has served the fewest: a (0 of 1), a (1 of 1), b, then a
    assert answers == ["a", "a", "b", "a"]


def test_no_replica_is_one_clear_error(bus):
    _, caller = bus
    replicas = Replicas(caller, SERVICE, wait_for_one=0.3)
    with pytest.raises(NoReplica, match="no echo replica answered twohr/r1/rpc/echo"):
        replicas.call("r1", QUERY, b"job")
    assert replicas.stats()["lost"] == 1
