"""The service shell on a real Zenoh router: queues, counters, health, malformed input."""

import os
import threading
import time

from twohr import keys
from twohr.bus import merged_health, open_session, query_health, wait_for_services
from twohr.messages import PoseMsg, decode, encode
from twohr.service import Counters, Inbox, Service, declare_publisher


class EchoService(Service):
    """Republishes every pose on the 'status' stream with its frame index, slowly."""

    name = "echo_test"

    def __init__(self, bus, delay=0.0, **kwargs):
        super().__init__(bus, **kwargs)
        self.delay = delay
        self.seen: list[int] = []

    def subscriptions(self):
        return [keys.all_robots("pose")]

    def handle(self, key, payload):
        pose, _ = decode(payload, PoseMsg)
        time.sleep(self.delay)
        self.seen.append(pose.frame_index)


def pose_payload(i, robot="r1"):
    return encode(PoseMsg(session_id="s", robot_id=robot, frame_index=i, stamp=float(i), position=[0, 0, 0],
                          orientation=[0, 0, 0, 1], status="tracking"))


def run_service(service):
    stop = threading.Event()
    thread = threading.Thread(target=service.run, args=(stop,), daemon=True)
    thread.start()
    return stop, thread


def test_inbox_policies():
    counters = Counters()
    box = Inbox(3, "drop_oldest", counters)
    for i in range(10):
        box.put(i)
    assert [box.get(0.01) for _ in range(3)] == [7, 8, 9] and counters.dropped == 7

    box = Inbox(2, "backpressure", Counters())
    got = []
    consumer = threading.Thread(target=lambda: [got.append(box.get(1.0)) for _ in range(20)])
    consumer.start()
    for i in range(20):
        box.put(i)  # blocks while full, never drops
    consumer.join()
    assert got == list(range(20))


def test_service_survives_malformed_messages_and_reports_health(bus_config):
    service = EchoService(bus_config)
    stop, thread = run_service(service)
    client = open_session(bus_config)
    try:
        wait_for_services(client, ["echo_test"], timeout=10)
        pub = declare_publisher(client, "twohr/r1/pose")
        for i in range(5):
            pub.put(pose_payload(i))
        for junk in (b"", b"garbage", pose_payload(99)[:-3], b"2HR\x01" + b"\xff" * 10):
            pub.put(junk)
        pub.put(pose_payload(5))
        deadline = time.time() + 10
        while len(service.seen) < 6 and time.time() < deadline:
            time.sleep(0.05)
        assert service.seen == [0, 1, 2, 3, 4, 5]
        health = query_health(client, "echo_test")
        assert health["malformed"] == 4 and health["processed"] == 6 and health["errors"] == 0
        assert thread.is_alive()
    finally:
        stop.set()
        thread.join(5)
        client.close()


def test_drop_oldest_under_overload_counts_drops(bus_config):
    service = EchoService(bus_config, delay=0.05, queue_size=2, policy="drop_oldest")
    service.name = "echo_drop_test"
    stop, thread = run_service(service)
    client = open_session(bus_config)
    try:
        wait_for_services(client, ["echo_drop_test"], timeout=10)
        pub = declare_publisher(client, "twohr/r2/pose")
        for i in range(40):
            pub.put(pose_payload(i, "r2"))
        time.sleep(1.5)
        c = service.counters.as_dict()
        assert c["received"] == 40
        assert c["dropped"] > 0 and c["processed"] + c["dropped"] + len(service.inbox) == 40
        assert service.seen == sorted(service.seen) and service.seen[-1] == 39  # freshest data wins
    finally:
        stop.set()
        thread.join(5)
        client.close()


def test_health_of_absent_service_is_none(bus_config):
    client = open_session(bus_config)
    try:
        assert query_health(client, "no_such_service", timeout=0.3) is None
    finally:
        client.close()



def test_control_and_queries_are_never_dropped_with_frames():
    """A drop-oldest inbox under a frame flood still delivers the urgent item, and first."""
    counters = Counters()
    inbox = Inbox(2, "drop_oldest", counters)
    inbox.put(("twohr/r/frames", 0))
    inbox.put(("twohr/r/control", "stop"), urgent=True)
    for i in range(1, 5):
        inbox.put(("twohr/r/frames", i))
    assert inbox.get(0.1) == ("twohr/r/control", "stop")
    assert [inbox.get(0.1), inbox.get(0.1), inbox.get(0.1)] == [("twohr/r/frames", 3), ("twohr/r/frames", 4), None]
    assert counters.dropped == 3


def test_services_take_their_cpu_priority_for_every_thread():
    """Each service takes the CPU priority of its work: the tracker first, the keyframe stages at a normal
    priority, the recorder lower. A change reaches every thread the process has, including threads that started
    before, and threads started later inherit it."""
    import subprocess
    import sys

    from twohr_services.detector.service import DetectorService
    from twohr_services.matcher.service import MatcherService
    from twohr_services.recorder.service import RecorderService
    from twohr_services.source.service import SourceService
    from twohr_services.tracker.service import TrackerService
    from twohr_services.yolo.service import YoloService

    # the map's work is never below a normal process of the robot: a busy process must not starve it
    assert [cls.priority for cls in (DetectorService, YoloService, MatcherService)] == ["keyframe"] * 3
    assert TrackerService.priority == "per_frame" and RecorderService.priority == "background"
    assert SourceService.priority == "normal"
    script = (
        "import os, threading, time\n"
        "from twohr.service import change_priority\n"
        "stop = threading.Event(); early = threading.Thread(target=stop.wait); early.start()\n"
        "base = os.getpriority(os.PRIO_PROCESS, 0)\n"
        "change_priority(7)\n"
        "late = []\n"
        "t = threading.Thread(target=lambda: late.append(os.getpriority(os.PRIO_PROCESS, 0)))\n"
        "t.start(); t.join()\n"
        "print(base, os.getpriority(os.PRIO_PROCESS, 0), os.getpriority(os.PRIO_PROCESS, early.native_id), late[0])\n"
        "stop.set()\n"
    )
    base, main, early, late = map(int, subprocess.check_output([sys.executable, "-c", script], text=True).split())
    assert (main, early, late) == (min(19, base + 7),) * 3


def test_the_per_frame_path_is_raised_where_the_process_may():
    """Raising priority needs root or CAP_SYS_NICE: with it every thread is raised, without it nothing changes
    and the call says so."""
    import subprocess
    import sys

    script = ("import os\nfrom twohr.service import change_priority\n"
              "base = os.getpriority(os.PRIO_PROCESS, 0)\nok = change_priority(-3)\n"
              "print(base, os.getpriority(os.PRIO_PROCESS, 0), int(ok))\n")
    base, after, ok = map(int, subprocess.check_output([sys.executable, "-c", script], text=True).split())
    may_raise = os.geteuid() == 0
    assert bool(ok) == may_raise
    assert after == (max(-20, base - 3) if may_raise else base)


def test_a_fair_inbox_serves_the_robots_in_turn():
    inbox = Inbox(16, "backpressure", Counters(), fair=True)
    for i in range(6):  # robot a floods, b sends little
        inbox.put(("twohr/a/frames", i))
    for i in range(2):
        inbox.put(("twohr/b/frames", i))
    inbox.put(("twohr/b/control", "stop"), urgent=True)
    order = [inbox.get(0.1) for _ in range(9)]
    assert order == [("twohr/b/control", "stop"), ("twohr/a/frames", 0), ("twohr/b/frames", 0),
                     ("twohr/a/frames", 1), ("twohr/b/frames", 1), ("twohr/a/frames", 2), ("twohr/a/frames", 3),
                     ("twohr/a/frames", 4), ("twohr/a/frames", 5)]
    assert inbox.get(0.01) is None
    plain = Inbox(16, "backpressure", Counters())
    for i in range(3):
        plain.put(("twohr/a/frames", i))
    plain.put(("twohr/b/frames", 0))
    assert [plain.get(0.1)[0] for _ in range(4)][-1] == "twohr/b/frames"  # FIFO: b waits behind all of a's


def test_replicas_answers_merge_counts_nested_counters_and_lists():
    answers = [
        {"service": "tracker", "replica": "h-1-tracker", "host": "h", "pid": 11, "processed": 5, "robots": ["a"],
         "ready": True, "jobs": {"detector": {"answered": {"r1": 3}, "lost": 0, "alive": ["r1", "r2"]}}},
        {"service": "tracker", "replica": "h-1-tracker-2", "host": "g", "pid": 12, "processed": 7, "robots": ["b"],
         "ready": True, "jobs": {"detector": {"answered": {"r1": 1, "r2": 4}, "lost": 2, "alive": ["r2", "r1"]}}},
    ]
    assert merged_health(answers) == {
        "service": "tracker", "processed": 12, "robots": ["a", "b"], "ready": True,
        "jobs": {"detector": {"answered": {"r1": 4, "r2": 4}, "lost": 2, "alive": ["r1", "r2"]}}}
    assert answers[0]["jobs"]["detector"]["answered"] == {"r1": 3}  # the replicas' own answers are left as they were


class SlowAnswers(Service):
    """Answers ``twohr/<robot>/rpc/echo/<replica>`` queries, each after ``hold`` is set: a service busy with a job."""

    name = "slow_test"

    def __init__(self, bus):
        super().__init__(bus)
        self.hold = threading.Event()

    def on_start(self):
        self.queryable = self.declare_replica_queryable("rpc/echo")

    def handle(self, key, query):
        self.hold.wait(30)
        query.reply(query.key_expr, b"done")


def test_a_robots_flood_of_queries_is_answered_busy_and_holds_up_no_other_robots(bus_config):
    from twohr.service import MAX_QUEUED_QUERIES

    service = SlowAnswers(bus_config)
    stop, thread = run_service(service)
    client = open_session(bus_config)
    try:
        wait_for_services(client, ["slow_test"], timeout=30)
        flood = [client.get(f"twohr/b/rpc/echo/{service.replica}", payload=pose_payload(i, "b"), timeout=60)
                 for i in range(MAX_QUEUED_QUERIES + 40)]
        # one query is being answered, MAX_QUEUED_QUERIES wait, the other 39 are answered busy at once
        deadline = time.monotonic() + 20
        while service.counters.dropped < 39:
            assert time.monotonic() < deadline, service.counters.as_dict()
            time.sleep(0.05)
        a = client.get(f"twohr/a/rpc/echo/{service.replica}", payload=pose_payload(0, "a"), timeout=60)
        time.sleep(0.5)
        assert len(service.inbox) <= MAX_QUEUED_QUERIES + 1, len(service.inbox)
        service.hold.set()
        assert [r.ok.payload.to_bytes() for r in a] == [b"done"]  # a's one query was queued and answered
        answers = [reply for replies in flood for reply in replies]
        busy = [r for r in answers if r.err is not None and b"busy" in r.err.payload.to_bytes()]
        assert len(busy) == 39 and len(answers) - len(busy) == MAX_QUEUED_QUERIES + 1, (len(answers), len(busy))
    finally:
        service.hold.set()
        client.close()
        stop.set()
        thread.join(10)
