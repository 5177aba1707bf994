"""Typed pub/sub over real Zenoh on loopback: between processes, through shared memory, with bad payloads."""

import dataclasses
import json
import time

import numpy as np
import pytest

from helpers_zenoh import router, spawn_python, wait_for
from shared import codec
from shared.codec import MessageError
from shared.messages import DepthFrame, Header, ImuSample, StreamEnd
from transport.pubsub import Publisher, Subscriber
from transport.session import open_session

# child process: publishes IMU samples and depth frames (shared memory as configured), then a StreamEnd
PUBLISHER_CHILD = r"""
import json, sys, time
import numpy as np
from shared.messages import DepthFrame, Header, ImuSample, StreamEnd
from transport.config import TransportConfig
from transport.pubsub import Publisher
from transport.session import open_session

cfg = TransportConfig(**json.loads(sys.argv[1]))
n = int(sys.argv[2])
with open_session(cfg) as s:
    imu = Publisher(s, cfg.namespace + "/imu", ImuSample, cfg, block=True)
    depth = Publisher(s, cfg.namespace + "/depth", DepthFrame, cfg)
    end = Publisher(s, cfg.namespace + "/end", StreamEnd, cfg)
    assert imu.wait_for_subscribers(10) and depth.wait_for_subscribers(10) and end.wait_for_subscribers(10)
    time.sleep(0.2)
    for i in range(n):
        imu.publish(ImuSample(header=Header(stamp_ns=1000 * i, seq=imu.next_seq, frame_id="S"),
                              omega_S=np.array([i, 0.5, -1.0]), acc_S=np.array([0.0, 0.0, 9.81 + i])))
    for i in range(3):
        rng = np.random.default_rng(i)
        d = rng.random((384, 512), dtype=np.float32)
        d[0, :4] = np.nan
        depth.publish(DepthFrame(header=Header(stamp_ns=i, seq=depth.next_seq, frame_id="cam0"), depth=d, sigma=d * 0.1,
                                 K=np.diag([400.0, 400.0, 1.0]), T_WC=np.eye(4), source="stereo"))
        time.sleep(0.02)
    time.sleep(0.1)
    end.publish(StreamEnd(header=Header(stamp_ns=0), source="child", frames_sent=n))
    time.sleep(0.3)
    print(json.dumps({"imu": imu.sent, "depth": depth.sent, "depth_shm": depth.sent_shm}), flush=True)
"""


def expected_depth(i):
    d = np.random.default_rng(i).random((384, 512), dtype=np.float32)
    d[0, :4] = np.nan
    return d


@pytest.mark.parametrize("shm,mode", [(True, "peer"), (False, "peer"), (True, "client")])
def test_typed_messages_between_processes(shm, mode):
    """Peers connect to the router and then to each other; clients go through the router. SHM works in both."""
    n = 200
    with router(shared_memory=shm, mode=mode) as cfg, open_session(cfg) as s:
        imu = Subscriber(s, cfg.namespace + "/imu", ImuSample, "all", 1000)
        depth = Subscriber(s, cfg.namespace + "/depth", DepthFrame, "all", 10)
        end = Subscriber(s, cfg.namespace + "/end", StreamEnd, "all", 2)
        child = spawn_python(PUBLISHER_CHILD, json.dumps(dataclasses.asdict(cfg)), str(n))
        out, err = child.communicate(timeout=30)
        assert child.returncode == 0, err
        sent = json.loads(out.splitlines()[-1])
        assert end.get(timeout=5).frames_sent == n
        samples = imu.drain()
        assert [m.header.seq for m in samples] == list(range(n))  # "all": nothing lost, in order
        assert all(m.omega_S[0] == m.header.seq and m.acc_S[2] == 9.81 + m.header.seq for m in samples)
        frames = depth.drain()
        assert len(frames) == 3
        for i, f in enumerate(frames):
            np.testing.assert_array_equal(f.depth, expected_depth(i))  # NaNs included, bit for bit
            np.testing.assert_array_equal(f.sigma, expected_depth(i) * 0.1)
            assert f.source == "stereo" and f.K[0, 0] == 400.0 and not f.depth.flags.writeable
        # shared memory carried the large frames when on, and never when off; IMU samples never
        assert sent["depth_shm"] == (3 if shm else 0)
        assert depth.received_shm == (3 if shm else 0) and imu.received_shm == 0
        assert imu.dropped == depth.dropped == 0
        for sub in (imu, depth, end):
            sub.close()


def test_peers_connected_to_one_router_find_each_other():
    with router() as cfg, open_session(cfg) as a, open_session(cfg) as b:
        assert wait_for(lambda: str(b.info.zid()) in {str(z) for z in a.info.peers_zid()}, 5)
        assert len(list(a.info.routers_zid())) == 1


def test_bad_payloads_are_counted_and_delivery_continues():
    with router() as cfg, open_session(cfg) as rx, open_session(cfg) as tx:
        key = cfg.namespace + "/imu"
        drops = []
        sub = Subscriber(rx, key, ImuSample, "all", 100, on_drop=lambda item, why: drops.append(why))
        pub = Publisher(tx, key, ImuSample, cfg)
        assert pub.wait_for_subscribers(5)
        good = codec.encode(ImuSample(header=Header(stamp_ns=1, seq=0), omega_S=np.zeros(3), acc_S=np.ones(3)))
        other = codec.encode(StreamEnd(header=Header(stamp_ns=1), source="x", frames_sent=0))
        rng = np.random.default_rng(1)
        garbage = [rng.bytes(200), good[: len(good) // 2], good[:10], b"SGMS" + rng.bytes(50), other,
                   good[:-48], b"x"]  # (the last 40 bytes are padding)
        pub.publish(ImuSample(header=Header(stamp_ns=0, seq=0), omega_S=np.zeros(3), acc_S=np.zeros(3)))
        for g in garbage:
            tx.put(key, g)
        for i in range(1, 4):
            pub.publish(ImuSample(header=Header(stamp_ns=i, seq=i), omega_S=np.full(3, i), acc_S=np.zeros(3)))
        assert wait_for(lambda: sub.received == 4 + len(garbage), 5)
        assert [m.header.seq for m in sub.drain()] == [0, 1, 2, 3]
        assert sub.dropped == len(garbage) and len(drops) == len(garbage)
        assert all(why.startswith("undecodable") for why in drops)
        assert any("expected ImuSample, got StreamEnd" in why for why in drops)
        with pytest.raises(MessageError, match="ImuSample"):
            pub.publish(StreamEnd(header=Header(stamp_ns=0), source="x", frames_sent=0))
        sub.close()
        pub.close()


def test_callback_mode_survives_a_failing_handler_and_latest_policy_drops_oldest():
    with router() as cfg, open_session(cfg) as rx, open_session(cfg) as tx:
        seen = []

        def handler(msg):
            if msg.header.seq == 1:
                raise RuntimeError("boom")
            seen.append(msg.header.seq)

        cb = Subscriber(rx, cfg.namespace + "/a", ImuSample, handler=handler)
        latest = Subscriber(rx, cfg.namespace + "/a", ImuSample, "latest", 2)
        pub = Publisher(tx, cfg.namespace + "/a", ImuSample, cfg, block=True)
        assert pub.wait_for_subscribers(5)
        time.sleep(0.1)
        for i in range(5):
            pub.publish(ImuSample(header=Header(stamp_ns=i, seq=i), omega_S=np.zeros(3), acc_S=np.zeros(3)))
        assert wait_for(lambda: len(seen) == 4 and latest.received == 5, 5)
        assert seen == [0, 2, 3, 4] and cb.handler_errors == 1 and cb.received == 5
        assert [m.header.seq for m in latest.drain()] == [3, 4] and latest.dropped == 3
        for x in (cb, latest, pub):
            x.close()


def test_shm_pool_exhaustion_falls_back_to_plain_bytes():
    with router(shm_pool_bytes=1 << 20, shm_threshold_bytes=1024) as cfg, open_session(cfg) as rx, open_session(cfg) as tx:
        got = []
        sub = Subscriber(rx, cfg.namespace + "/d", DepthFrame, handler=got.append)
        # block: the 3 MB fallback must not be dropped by congestion control on a busy machine (what is tested is the
        # fallback; it failed once in `make test` at 22:45 on 2026-12-07 with the default, dropping)
        pub = Publisher(tx, cfg.namespace + "/d", DepthFrame, cfg, block=True)
        assert pub.wait_for_subscribers(5)
        big = np.arange(384 * 512, dtype=np.float32).reshape(384, 512)  # 1.5 MB > 1 MiB pool
        small = np.ones((16, 16), np.float32)  # about 2.5 kB: above the 1024 B threshold
        for arr in (big, small):
            pub.publish(DepthFrame(header=Header(stamp_ns=0), depth=arr, sigma=arr, K=np.eye(3), T_WC=np.eye(4), source="t"))
        assert wait_for(lambda: len(got) == 2, 5)
        np.testing.assert_array_equal(got[0].depth, big)
        assert pub.shm_fallbacks == 1 and pub.sent_shm == 1 and pub.sent == 2
        sub.close()
        pub.close()


def test_no_shm_pool_where_memory_cannot_be_locked_sends_plain_bytes(monkeypatch, caplog):
    """An unprivileged process under a small RLIMIT_MEMLOCK (containers) cannot make the pool: it publishes anyway."""
    import zenoh.shm

    class NoPool:
        @staticmethod
        def default_backend(pool_bytes):
            raise zenoh.ZError("Unable to create POSIX shm segment: OS error 12")

    monkeypatch.setattr(zenoh.shm, "ShmProvider", NoPool)
    pool = (1 << 20) + 4096  # a size no other test's pool has: this process's provider cache is keyed by size
    with router(shm_pool_bytes=pool, shm_threshold_bytes=1024) as cfg, open_session(cfg) as rx, open_session(cfg) as tx:
        got = []
        sub = Subscriber(rx, cfg.namespace + "/d", DepthFrame, handler=got.append)
        pub = Publisher(tx, cfg.namespace + "/d", DepthFrame, cfg)
        assert pub.wait_for_subscribers(5)
        arr = np.ones((64, 64), np.float32)
        pub.publish(DepthFrame(header=Header(stamp_ns=0), depth=arr, sigma=arr, K=np.eye(3), T_WC=np.eye(4), source="t"))
        assert wait_for(lambda: len(got) == 1, 5)
        assert pub.sent == 1 and pub.sent_shm == 0
        assert "no shared memory in this process" in caplog.text
        sub.close()
        pub.close()


def test_a_handler_knows_when_its_message_was_sent_however_late_it_runs():
    """Latencies from send times (services/app/metrics/latency.py): each sample carries its publisher's clock at put;
    a handler held up by the one before it sees its message late, but the send time stays the put's."""
    from services.app.metrics.latency import ArrivalLog
    from transport.pubsub import sample_sent_ns

    with router() as cfg, open_session(cfg) as rx, open_session(cfg) as tx:
        log, put_ns = ArrivalLog(), {}
        record = log.handler("imu", sent=sample_sent_ns)

        def slow_first(msg):
            record(msg)
            if msg.header.seq == 0:
                time.sleep(0.2)  # the next message waits behind this callback

        sub = Subscriber(rx, cfg.namespace + "/a", ImuSample, handler=slow_first)
        pub = Publisher(tx, cfg.namespace + "/a", ImuSample, cfg, block=True)
        assert pub.wait_for_subscribers(5)
        time.sleep(0.1)
        for i in range(2):
            put_ns[i] = time.time_ns()
            pub.publish(ImuSample(header=Header(stamp_ns=i, seq=i), omega_S=np.zeros(3), acc_S=np.zeros(3)))
        assert wait_for(lambda: len(log.get("imu")[0]) == 2, 5)
        stamps, arrived = log.get("imu")
        _, sent = log.get_sent("imu")
        for s, a, t in zip(stamps.tolist(), arrived.tolist(), sent.tolist()):
            assert put_ns[s] - 1_000_000 <= t <= put_ns[s] + 20_000_000  # the put's time, not the callback's
            assert t <= a + 1_000_000
        assert arrived[1] - put_ns[1] > 150_000_000 > sent[1] - put_ns[1]
        assert sample_sent_ns() is None  # outside a handler
        sub.close()
        pub.close()


# child process: counts the samples of one key until told to stop (a line on stdin), then prints the count
COUNTING_CHILD = r"""
import json, sys, time
from transport.config import TransportConfig
from transport.session import open_session

cfg = TransportConfig(**json.loads(sys.argv[1]))
count = [0]
with open_session(cfg) as s:
    sub = s.declare_subscriber(cfg.namespace + "/depth", lambda _s: count.__setitem__(0, count[0] + 1))
    print("ready", flush=True)
    sys.stdin.readline()
    print(count[0], flush=True)
"""


@pytest.mark.parametrize("mode", ["client", "peer"])
def test_large_latest_messages_wait_for_room_rather_than_vanish(mode):
    """A burst of 1.5 MB messages of a topic that may drop, over TCP without shared memory (as between containers),
    to a subscriber process that gets no CPU for 0.3 s (SIGSTOP: a starved container): with Zenoh's 1 ms
    wait_before_drop most of them vanish, uncounted; with transport.drop_wait_ms 2000 every one arrives
    (configs/docker.yaml sets 20 ms, enough for the frames there)."""
    import signal
    import subprocess
    import threading

    n = 30
    got = {}
    for wait_ms in (1.0, 2000.0):
        with router(mode=mode, shared_memory=False, drop_wait_ms=wait_ms) as cfg, open_session(cfg) as a:
            child = spawn_python(COUNTING_CHILD, json.dumps(dataclasses.asdict(cfg)), stdin=subprocess.PIPE)
            try:
                assert child.stdout.readline().strip() == "ready"
                pub = Publisher(a, cfg.namespace + "/depth", DepthFrame, cfg)
                assert pub.wait_for_subscribers(10)
                time.sleep(0.3)
                d = np.ones((384, 512), np.float32)
                child.send_signal(signal.SIGSTOP)
                threading.Timer(0.3, lambda: child.send_signal(signal.SIGCONT)).start()
                for i in range(n):
                    pub.publish(DepthFrame(header=Header(stamp_ns=i, seq=i, frame_id="C"), depth=d, sigma=d,
                                           K=np.eye(3), T_WC=np.eye(4), source="stereo"))
                time.sleep(1.0)
                out, _ = child.communicate("stop\n", timeout=20)
                got[wait_ms] = int(out.split()[-1])
            finally:
                child.send_signal(signal.SIGCONT)
                child.kill()
    assert got[2000.0] == n, got
    assert got[1.0] < n, got
