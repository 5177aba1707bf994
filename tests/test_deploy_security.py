"""Security of a networked deployment: loopback-only defaults, mutual TLS, user/password, access control.

A real ``sigmaslam router`` process runs with the configs that tools/secure_setup.py generates
(certificates made with openssl); services join as Zenoh clients with their own identities.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import psutil
import pytest
import zenoh

from shared import topics
from shared.messages import EstimatorState, EstimatorWindow, FeatureFrame, Header
from tests.helpers_zenoh import REPO, child_env, free_port, wait_for
from tools import secure_setup
from transport.config import TransportConfig
from transport.node import Node
from transport.session import open_session, zenoh_config

pytestmark = pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl is not installed")
NS = "sigmaslam/robot0"


def _loopback(endpoint: str) -> bool:
    host = endpoint.split("/", 1)[1].rsplit(":", 1)[0]
    return host in ("127.0.0.1", "localhost", "[::1]")


def test_defaults_listen_on_loopback_only() -> None:
    cfg = TransportConfig()
    assert not cfg.multicast_scouting
    for role in ("service", "router"):
        zc = zenoh_config(cfg, role)
        listen = json.loads(zc.get_json("listen/endpoints"))
        assert listen and all(_loopback(e) for e in listen), (role, listen)
        assert json.loads(zc.get_json("scouting/multicast/enabled")) is False
    assert all(_loopback(e) for e in cfg.connect)
    # a real session with the defaults: every socket it listens on is bound to loopback
    with open_session(dataclasses.replace(cfg, connect=[])):
        listening = [c.laddr for c in psutil.Process().net_connections("inet") if c.status == psutil.CONN_LISTEN
                     or (c.type == 2 and not c.raddr)]
        assert listening, "the peer session should listen somewhere"
        assert all(addr.ip in ("127.0.0.1", "::1") for addr in listening), listening


# ----------------------------------------------------------------------------- secured router

@dataclasses.dataclass
class Deployment:
    endpoint: str
    configs: Path

    def cfg(self, identity: str | None, **kw: object) -> TransportConfig:
        json5 = str(self.configs / f"{identity}.json5") if identity else ""
        fields = dict(namespace=NS, mode="client", connect=[self.endpoint], zenoh_json5=json5, heartbeat_period_s=0.2)
        fields.update(kw)
        return TransportConfig(**fields)


def _start_router(configs: Path, port: int) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-m", "services.app.cli", "router", "--listen", f"tls/localhost:{port}",
                             "--set", f"transport.zenoh_json5={configs / 'router.json5'}"],
                            cwd=REPO, env=child_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    line = proc.stdout.readline()
    assert "listening" in line, proc.stderr.read()[-2000:] if proc.poll() is not None else line
    return proc


@pytest.fixture(scope="module")
def certs(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("certs")
    secure_setup.make_certs(d, tuple(secure_setup.PUBLISHES))
    return d


@pytest.fixture(scope="module", params=["usrpwd+mtls", "mtls"])
def deployment(request, certs, tmp_path_factory):
    configs = tmp_path_factory.mktemp("configs")
    ids = tuple(secure_setup.PUBLISHES)
    passwords = secure_setup.make_credentials(certs, ids) if request.param == "usrpwd+mtls" else None
    secure_setup.write_configs(configs, str(certs), NS, ids, passwords)
    port = free_port()
    router = _start_router(configs, port)
    try:
        yield Deployment(f"tls/localhost:{port}", configs)
    finally:
        router.terminate()
        router.wait(10)


def _collector(session: zenoh.Session, key: str) -> list[str]:
    got: list[str] = []
    session.declare_subscriber(key, lambda s: got.append(str(s.key_expr)))
    return got


def test_client_without_identity_cannot_connect(deployment: Deployment, certs: Path, tmp_path: Path) -> None:
    # plain TCP to the TLS endpoint, TLS without a client certificate, a certificate from another CA
    with pytest.raises(zenoh.ZError):
        open_session(deployment.cfg(None, connect=[deployment.endpoint.replace("tls/", "tcp/")]))
    ca_only = tmp_path / "ca_only.json5"
    ca_only.write_text(json.dumps({"transport": {"link": {"tls": {"root_ca_certificate": str(certs / "ca.crt")}}}}))
    with pytest.raises(zenoh.ZError):
        open_session(deployment.cfg(None, zenoh_json5=str(ca_only)))
    rogue = tmp_path / "rogue"
    secure_setup.make_certs(rogue, ("frontend",))
    cfg = json.loads((deployment.configs / "frontend.json5").read_text().split("\n", 1)[1])
    cfg["transport"]["link"]["tls"].update(connect_private_key=str(rogue / "frontend.key"),
                                           connect_certificate=str(rogue / "frontend.crt"))
    rogue_cfg = tmp_path / "rogue.json5"
    rogue_cfg.write_text(json.dumps(cfg))
    with pytest.raises(zenoh.ZError):
        open_session(deployment.cfg(None, zenoh_json5=str(rogue_cfg)))


def test_wrong_password_cannot_connect(deployment: Deployment, tmp_path: Path) -> None:
    cfg = json.loads((deployment.configs / "frontend.json5").read_text().split("\n", 1)[1])
    if "auth" not in cfg["transport"]:
        pytest.skip("this deployment authenticates by certificate only")
    cfg["transport"]["auth"]["usrpwd"]["password"] = "guess"
    path = tmp_path / "wrong.json5"
    path.write_text(json.dumps(cfg))
    with pytest.raises(zenoh.ZError):
        open_session(deployment.cfg(None, zenoh_json5=str(path)))


def test_unauthenticated_peer_can_neither_subscribe_nor_publish(deployment: Deployment, certs: Path,
                                                                tmp_path: Path) -> None:
    """A peer session opens even when its connection is refused; it still sees and reaches nothing."""
    ca_only = tmp_path / "ca_only.json5"
    ca_only.write_text(json.dumps({"transport": {"link": {"tls": {"root_ca_certificate": str(certs / "ca.crt")}}}}))
    intruder_cfg = deployment.cfg(None, mode="peer", listen=["tcp/127.0.0.1:0"], zenoh_json5=str(ca_only))
    with open_session(deployment.cfg("backend")) as backend, open_session(deployment.cfg("frontend")) as frontend, \
            open_session(intruder_cfg) as intruder:
        backend_got = _collector(backend, f"{NS}/**")
        intruder_got = _collector(intruder, f"{NS}/frontend/**")
        time.sleep(0.5)
        intruder.put(f"{NS}/estimator/state", b"forged")
        for _ in range(5):
            frontend.put(f"{NS}/frontend/frame", b"real")
            time.sleep(0.05)
        assert wait_for(lambda: len(backend_got) >= 5, 5.0)
        time.sleep(0.3)
        assert backend_got == [f"{NS}/frontend/frame"] * 5, "the intruder's publication got through"
        assert intruder_got == [], "the intruder received data"


def _state(i: int) -> EstimatorState:
    return EstimatorState(header=Header(stamp_ns=i, seq=i, frame_id="W"), T_WS=np.eye(4), v_W=np.zeros(3),
                          gyro_bias=np.zeros(3), acc_bias=np.zeros(3), covariance=np.eye(15))


def _features(i: int) -> FeatureFrame:
    return FeatureFrame(header=Header(stamp_ns=i, seq=i, frame_id="cam0"), landmark_ids=np.arange(3),
                        camera_index=np.zeros(3, np.int16), uv=np.ones((3, 2), np.float32),
                        p_W_init=np.zeros((3, 3)), is_keyframe=False)


def _window(i: int) -> EstimatorWindow:
    return EstimatorWindow(header=Header(stamp_ns=i, seq=i, frame_id="W"), T_WS=np.eye(4), v_W=np.zeros(3),
                           gyro_bias=np.zeros(3), acc_bias=np.zeros(3), T_corr=np.eye(4),
                           landmark_ids=np.zeros(0, np.int64), p_W=np.zeros((0, 3)))


def test_service_publishes_only_its_own_keys(deployment: Deployment) -> None:
    with Node("backend", deployment.cfg("backend"), handle_signals=False) as backend:
        features = backend.subscriber(topics.FEATURES)
        windows = backend.subscriber(topics.WINDOW)
        with Node("frontend", deployment.cfg("frontend"), handle_signals=False) as frontend:
            own, foreign = frontend.publisher(topics.FEATURES), frontend.publisher(topics.WINDOW)
            assert own.wait_for_subscribers(5.0)
            for i in range(10):
                own.publish(_features(i))
                foreign.publish(_window(i))
                time.sleep(0.02)
            assert wait_for(lambda: features.received >= 10, 5.0), features.received
            time.sleep(0.3)
            assert windows.received == 0, "frontend published on the backend's key"
        # the backend itself may publish its state
        with Node("viewer", deployment.cfg("viewer"), handle_signals=False) as viewer:
            seen = viewer.subscriber(topics.STATE)
            pub = backend.publisher(topics.STATE)
            assert pub.wait_for_subscribers(5.0)
            # matching can be reported a moment before the router forwards to the new subscriber:
            # publish until one arrives (the ACL check above is what a lost sample must not mask)
            deadline = time.monotonic() + 10.0
            while seen.received == 0 and time.monotonic() < deadline:
                pub.publish(_state(1))
                wait_for(lambda: seen.received >= 1, 0.5)
            assert seen.received >= 1


def _health(deployment: Deployment, service: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "services.app.cli", "health", service, "--timeout", "3",
                           "--set", f"transport.connect=[{deployment.endpoint}]",
                           "--set", f"transport.zenoh_json5={deployment.configs / 'operator.json5'}"],
                          cwd=REPO, env=child_env(), capture_output=True, text=True, timeout=60)


def test_health_sees_own_heartbeat_but_not_an_impersonation(deployment: Deployment) -> None:
    done = threading.Event()

    def run(name: str, identity: str) -> None:
        with Node(name, deployment.cfg(identity), handle_signals=False) as node:
            done.wait(20.0)
            node.stop()

    threads = [threading.Thread(target=run, args=("frontend", "frontend")),
               threading.Thread(target=run, args=("backend", "frontend"))]  # frontend's identity posing as backend
    for t in threads:
        t.start()
    try:
        ok = _health(deployment, "frontend")
        assert ok.returncode == 0, ok.stderr
        forged = _health(deployment, "backend")
        assert forged.returncode == 1 and "no heartbeat" in forged.stderr
    finally:
        done.set()
        for t in threads:
            t.join(10)


def test_committed_configs_match_the_generator(tmp_path: Path) -> None:
    committed = REPO / "configs" / "secure"
    secure_setup.write_configs(tmp_path, "secrets", NS, tuple(secure_setup.PUBLISHES))
    names = sorted(p.name for p in tmp_path.glob("*.json5"))
    assert names == sorted(p.name for p in committed.glob("*.json5"))
    for name in names:
        assert (committed / name).read_text() == (tmp_path / name).read_text(), f"configs/secure/{name} is stale"
