"""`sigmaslam up`: restart bookkeeping (pure), and real processes: a SIGKILLed child comes back with
a new pid, a crashing child is given up on, SIGTERM (or SIGKILL of the supervisor) leaves no child."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading

import psutil
import pytest
import yaml

from helpers_zenoh import REPO, child_env, free_port, service_config, wait_for
from services.recorder.mcap_reader import read_metadata
from services.app.supervisor import Child, RestartTracker, ServiceSpec, Supervisor, SupervisorConfig, describe_exit, validate
from services.app.system_config import load_system_config
from shared.config import ConfigError, to_dict


# ----------------------------------------------------------------------------- bookkeeping, no processes

def test_restart_backoff_doubles_then_gives_up():
    tr = RestartTracker(ServiceSpec(name="a", argv=["x"], max_restarts=3, window_s=60.0, backoff_s=0.5, backoff_max_s=1.5))
    delays = [tr.on_exit(-9, now=t) for t in (0.0, 1.0, 2.0)]
    assert [d.restart for d in delays] == [True, True, True]
    assert [d.delay_s for d in delays] == [0.5, 1.0, 1.5]  # doubling, capped at backoff_max_s
    last = tr.on_exit(1, now=5.0)
    assert not last.restart and tr.gave_up and "giving up" in last.reason
    assert tr.total_restarts == 3


def test_restarts_outside_the_window_do_not_count():
    tr = RestartTracker(ServiceSpec(name="a", argv=["x"], max_restarts=2, window_s=10.0, backoff_s=0.0))
    assert tr.on_exit(1, 0.0).restart and tr.on_exit(1, 1.0).restart
    assert not tr.on_exit(1, 2.0).restart  # third failure within 10 s
    tr2 = RestartTracker(ServiceSpec(name="b", argv=["x"], max_restarts=2, window_s=10.0, backoff_s=0.0))
    assert tr2.on_exit(1, 0.0).restart and tr2.on_exit(1, 1.0).restart
    assert tr2.on_exit(1, 10.5).restart  # the restart at 0 s left the window
    assert not tr2.on_exit(1, 10.6).restart


def test_policies():
    on_failure = RestartTracker(ServiceSpec(name="a", argv=["x"]))
    assert not on_failure.on_exit(0, 0.0).restart and not on_failure.gave_up
    assert on_failure.on_exit(-signal.SIGKILL, 0.0).restart
    assert RestartTracker(ServiceSpec(name="a", argv=["x"], restart="always")).on_exit(0, 0.0).restart
    assert not RestartTracker(ServiceSpec(name="a", argv=["x"], restart="never")).on_exit(1, 0.0).restart
    assert describe_exit(-9) == "killed by SIGKILL" and describe_exit(3) == "exit code 3"


def test_validate_rejects_bad_specs():
    ok = ServiceSpec(name="rec", argv=["record"])
    validate(SupervisorConfig(services=[ok]), {"record": None})
    for bad, word in [([ok, ok], "unique"), ([ServiceSpec(name="x", argv=[])], "argv"),
                      ([ServiceSpec(name="x", argv=["nope"])], "not a sigmaslam subcommand")]:
        with pytest.raises(ConfigError, match=word):
            validate(SupervisorConfig(services=bad), {"record": None})
    # the restart policy is an enumeration: the config loader refuses a bad one, naming the item
    with pytest.raises(ConfigError, match=r"supervisor.services\[0\].restart: 'sometimes' is not one of the allowed"):
        load_system_config(None, ["supervisor.services=[{name: x, argv: [record], restart: sometimes}]"])


def test_children_get_the_malloc_thresholds_unless_the_environment_sets_them(tmp_path, monkeypatch):
    for name in ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_"):
        monkeypatch.delenv(name, raising=False)
    env = Supervisor(SupervisorConfig(start_router=False), tmp_path / "c.yaml", tmp_path)._env()
    assert env["MALLOC_MMAP_THRESHOLD_"] == str(32 << 20) and env["MALLOC_TRIM_THRESHOLD_"] == str(256 << 20)
    monkeypatch.setenv("MALLOC_TRIM_THRESHOLD_", "12345")  # the user's own choice wins
    env = Supervisor(SupervisorConfig(start_router=False, malloc_mmap_threshold_mb=0), tmp_path / "c.yaml",
                     tmp_path)._env()
    assert "MALLOC_MMAP_THRESHOLD_" not in env and env["MALLOC_TRIM_THRESHOLD_"] == "12345"
    with pytest.raises(ConfigError, match="0..32 MiB"):
        validate(SupervisorConfig(malloc_mmap_threshold_mb=64))


# ----------------------------------------------------------------------------- real processes

class Up:
    """`sigmaslam up CONFIG` in a subprocess, its output collected line by line."""

    def __init__(self, tmp_path, services: list[dict], start_router: bool = True) -> None:
        port = free_port()
        self.tcfg = service_config(port)
        cfg = {"transport": to_dict(self.tcfg),
               "supervisor": {"services": services, "start_router": start_router, "router_startup_s": 0.2,
                              "shutdown_timeout_s": 5.0, "run_dir": str(tmp_path / "runs")}}
        path = tmp_path / "system.yaml"
        path.write_text(yaml.safe_dump(cfg))
        self.proc = subprocess.Popen([sys.executable, "-m", "services.app.cli", "up", str(path)], cwd=REPO, env=child_env(),
                                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        self.lines: list[str] = []
        threading.Thread(target=lambda: self.lines.extend(iter(self.proc.stdout.readline, "")), daemon=True).start()

    def pids(self, name: str) -> list[int]:
        pat = re.compile(rf"\[sigmaslam up\] {name}: started pid (\d+)")
        return [int(m.group(1)) for line in list(self.lines) if (m := pat.search(line))]

    def text(self) -> str:
        return "".join(self.lines)

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


def gone(pid: int) -> bool:
    try:
        return psutil.Process(pid).status() == psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return True


def test_up_restarts_a_killed_child_and_stops_everything_on_sigterm(tmp_path):
    out = tmp_path / "rec.mcap"
    up = Up(tmp_path, [{"name": "rec", "argv": ["record", "--out", str(out)], "backoff_s": 0.1}])
    try:
        assert wait_for(lambda: len(up.pids("rec")) == 1 and len(up.pids("router")) == 1, 20.0), up.text()
        first = up.pids("rec")[0]
        child = psutil.Process(first)
        assert child.ppid() == up.proc.pid and child.pid != up.proc.pid
        # its own process group (a terminal's Ctrl-C reaches the supervisor only, which stops the children in
        # order) in the supervisor's session: the recorder (nice 10) is not on the path to a pose, so it shares the
        # supervisor's scheduling group, ranked there by its nice (the next test)
        assert os.getpgid(first) == first and os.getsid(first) == os.getsid(up.proc.pid)
        cmd = child.cmdline()  # python -m services.app.cli record <run>/config.yaml --out rec.mcap
        assert cmd[1:4] == ["-m", "services.app.cli", "record"] and cmd[4].endswith("config.yaml") and cmd[5:] == ["--out", str(out)]
        assert wait_for(lambda: out.exists(), 20.0), up.text()  # the recorder got going
        child.send_signal(signal.SIGKILL)
        assert wait_for(lambda: len(up.pids("rec")) == 2, 20.0), up.text()
        second = up.pids("rec")[1]
        assert second != first and gone(first)
        assert "killed by SIGKILL; restarting" in up.text()
        children = [second, up.pids("router")[0]]
        assert all(psutil.pid_exists(p) for p in children)
        # the restarted recorder has its own file open (the relayed output of the two children may interleave
        # with the supervisor's lines, so wait for the file rather than for a "recording" line)
        assert wait_for(lambda: (tmp_path / "rec.1.mcap").exists(), 20.0), up.text()
        up.proc.send_signal(signal.SIGTERM)
        up.proc.wait(timeout=15)
        assert up.proc.returncode == 0, up.text()
        assert all(wait_for(lambda p=p: gone(p), 5.0) for p in children), up.text()
    finally:
        up.close()
    # the restarted recorder got SIGTERM and closed its file (rec.1.mcap: it never overwrites the cut rec.mcap
    # of its killed predecessor): it reads back, with the config the supervisor wrote
    assert out.exists()
    meta = read_metadata(tmp_path / "rec.1.mcap")
    assert meta["supervisor"]["services"][0]["name"] == "rec"
    assert meta["transport"]["namespace"] == up.tcfg.namespace


def test_up_gives_up_after_max_restarts(tmp_path):
    # `sigmaslam config --set no_such.key=1` fails at once with exit code 2
    up = Up(tmp_path, [{"name": "bad", "argv": ["config", "--set", "no_such.key=1"], "max_restarts": 2,
                        "backoff_s": 0.05}], start_router=False)
    try:
        up.proc.wait(timeout=30)
    finally:
        up.close()
    assert up.proc.returncode == 1, up.text()
    assert len(up.pids("bad")) == 3  # the first run plus max_restarts restarts
    assert up.text().count("exit code 2; restarting") == 2 and "giving up" in up.text()


def test_children_die_with_a_sigkilled_supervisor(tmp_path):
    up = Up(tmp_path, [{"name": "rec", "argv": ["record", "--out", str(tmp_path / "r.mcap")]}])
    try:
        assert wait_for(lambda: len(up.pids("rec")) == 1 and len(up.pids("router")) == 1, 20.0), up.text()
        children = up.pids("rec") + up.pids("router")
        up.proc.kill()
        up.proc.wait()
        assert all(wait_for(lambda p=p: gone(p), 10.0) for p in children), up.text()
    finally:
        up.close()


def test_stop_timeout_per_service(tmp_path):
    """A service with its own stop_timeout_s may take longer than shutdown_timeout_s to exit after SIGTERM
    (the mapping writes its map then); one without it is SIGKILLed at shutdown_timeout_s, after it was asked for
    its threads' stacks (as every process command registers them: services/app/process_cmd.py), so the log says
    where it hung."""
    from services.app.process_cmd import STACKS_SIGNAL

    slow_exit = ("import faulthandler, signal, sys, time\n"
                 f"faulthandler.register({int(STACKS_SIGNAL)}, all_threads=True)\n"
                 "def stuck_in_shutdown(*a):\n"
                 "    time.sleep(1.5)\n"
                 "    sys.exit(0)\n"
                 "signal.signal(signal.SIGTERM, stuck_in_shutdown)\n"
                 "print('ready', flush=True)\n"
                 "time.sleep(60)\n")
    sup = Supervisor(SupervisorConfig(start_router=False, shutdown_timeout_s=0.5), tmp_path / "c.yaml", tmp_path)
    patient = Child(ServiceSpec(name="patient", argv=["x"], stop_timeout_s=10.0), [])
    hasty = Child(ServiceSpec(name="hasty", argv=["x"]), [])
    for c in (patient, hasty):
        c.proc = subprocess.Popen([sys.executable, "-c", slow_exit], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                  text=True, start_new_session=True)
        assert c.proc.stdout.readline().strip() == "ready"
    sup.children = [patient, hasty]
    sup.shutdown()
    assert patient.proc.returncode == 0  # finished its SIGTERM handler
    assert hasty.proc.returncode == -signal.SIGKILL
    stacks = hasty.proc.stderr.read()
    assert "stuck_in_shutdown" in stacks, stacks
    assert "stuck_in_shutdown" not in patient.proc.stderr.read()
    with pytest.raises(ConfigError, match="stop_timeout_s"):
        validate(SupervisorConfig(services=[ServiceSpec(name="x", argv=["record"], stop_timeout_s=-1.0)]), {"record": None})


@pytest.mark.service
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="scheduling classes and autogroups are Linux's")
def test_children_get_a_session_nice_class_and_group_nice_of_their_own(tmp_path):
    """What the supervisor gives each child: the nice of its spec added to the supervisor's (down to the lowest
    allowed here) and its scheduling class; a child asked for a nice below 0 (the path to a pose) also a session of
    its own, a scheduling autogroup with that nice, so that it ranks against other programs' processes by it; the
    others stay in the supervisor's session and group."""
    import os

    from services.app.scheduling import autogroup_nice, lowest_nice

    probe = ("import os, sys\n"
             "from services.app.scheduling import autogroup_nice\n"
             "g = autogroup_nice()\n"
             "open(sys.argv[1], 'w').write(f'{os.getsid(0) == os.getpid()} {os.getpriority(os.PRIO_PROCESS, 0)} '\n"
             "                             f'{os.sched_getscheduler(0)} {\"none\" if g is None else g}')\n")
    base, low = os.getpriority(os.PRIO_PROCESS, 0), lowest_nice()
    mine = autogroup_nice()
    sup = Supervisor(SupervisorConfig(start_router=False), tmp_path / "c.yaml", tmp_path)
    for sched, nice, policy in (("idle", 0, os.SCHED_IDLE), ("batch", 3, os.SCHED_BATCH), ("normal", 19, os.SCHED_OTHER),
                                ("normal", -10, os.SCHED_OTHER)):
        result = tmp_path / f"{sched}{nice}.txt"
        child = Child(ServiceSpec(name="probe", argv=["x"], nice=nice, sched=sched),
                      [sys.executable, "-c", probe, str(result)])
        sup._start(child)
        assert child.proc.wait(timeout=30) == 0
        out = result.read_text()
        own_session, got_nice, got_policy, group = out.split()
        want = max(low, min(19, base + nice))
        assert own_session == str(nice < 0) and int(got_nice) == want and int(got_policy) == policy, (sched, nice, out)
        if group != "none":
            assert int(group) == (want if nice < 0 else mine), (sched, nice, out)


@pytest.mark.service
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="SCHED_FIFO and RLIMIT_RTPRIO are Linux's")
def test_a_fifo_child_runs_real_time_where_allowed_and_at_its_nice_where_not(tmp_path):
    """The frontend's class: SCHED_FIFO at supervisor.realtime_priority where this process may grant it, its threads
    too; realtime_priority 0, or a priority above what is allowed, gives the normal class at its nice, and the
    status line says why."""
    import os

    from services.app.scheduling import highest_rt_priority, resolve_sched

    probe = ("import os, sys, threading\n"
             "got = []\n"
             "t = threading.Thread(target=lambda: got.append(os.sched_getscheduler(0)))\n"
             "t.start(); t.join()\n"
             "open(sys.argv[1], 'w').write(f'{os.sched_getscheduler(0)} {os.sched_getparam(0).sched_priority} {got[0]}')\n")
    allowed = highest_rt_priority()
    for priority in (10, 0):
        sup = Supervisor(SupervisorConfig(start_router=False, realtime_priority=priority), tmp_path / "c.yaml",
                         tmp_path)
        result = tmp_path / f"fifo{priority}.txt"
        child = Child(ServiceSpec(name="probe", argv=["x"], nice=-10, sched="fifo"),
                      [sys.executable, "-c", probe, str(result)])
        sup._start(child)
        assert child.proc.wait(timeout=30) == 0
        policy, prio, thread_policy = map(int, result.read_text().split())
        if 0 < priority <= allowed:
            assert (policy, prio, thread_policy) == (os.SCHED_FIFO, priority, os.SCHED_FIFO)
        else:
            assert (policy, prio) == (os.SCHED_OTHER, 0)
    # the fallback and its reason, whatever this machine allows
    assert resolve_sched("fifo", 10, highest=99) == ("fifo", 10, "")
    sched, prio, why = resolve_sched("fifo", 10, highest=0)
    assert (sched, prio) == ("normal", 0) and "ulimit -r 10" in why
    assert resolve_sched("batch", 10, highest=99) == ("batch", 0, "")
    with pytest.raises(ConfigError, match="realtime_priority"):
        validate(SupervisorConfig(realtime_priority=100, services=[ServiceSpec(name="x", argv=["record"])]),
                 {"record": None})
