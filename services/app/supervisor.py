"""Process supervisor behind ``sigmaslam up``: one OS process per service, bounded restarts.

Each enabled :class:`ServiceSpec` (its unset scheduling taken from its process's description:
:func:`services.app.processes.with_defaults`) runs as ``[sys.executable, "-m", "services.app.cli", argv[0], CONFIG,
*argv[1:]]`` in its own process group (the path to a pose, nice < 0: in a session and scheduling group of its own,
services/app/scheduling.py), where CONFIG is the resolved system config the
supervisor wrote to ``<run_dir>/config.yaml`` (also in ``$SIGMASLAM_CONFIG``; ``$SIGMASLAM_RUN_DIR``
is the run folder; ``$SIGMASLAM_RESTARTS`` counts the restarts of that service, 0 at its first start). With ``start_router`` the router (``sigmaslam router CONFIG``) starts first.

A child that exits is logged with its exit code or signal. It is restarted (after a backoff that
doubles per recent restart) when its policy says so, at most ``max_restarts`` times within
``window_s``; beyond that the supervisor gives up on it (logged). The bookkeeping is
:class:`RestartTracker`, which needs no processes. On SIGINT/SIGTERM every service gets SIGTERM,
then SIGKILL after ``shutdown_timeout_s``; the router is stopped last. Children also get SIGTERM
(``prctl(PR_SET_PDEATHSIG)``, Linux) when the supervisor dies for any reason, SIGKILL included.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from services.app.config import ServiceSpec, SupervisorConfig
from services.app.processes import with_defaults
from services.app.scheduling import apply_in_child, resolve_scheduling
from shared.config import ConfigError
from services.app.supervision import RESTARTS_ENV

log = logging.getLogger("sigmaslam.up")


# ----------------------------------------------------------------------------- restart bookkeeping

@dataclasses.dataclass(frozen=True)
class Decision:
    restart: bool
    delay_s: float = 0.0
    reason: str = ""


class RestartTracker:
    """Restart decisions for one service from its exit history (pure: times are passed in)."""

    def __init__(self, spec: ServiceSpec) -> None:
        self.spec = spec
        self._restarts: collections.deque[float] = collections.deque()
        self.total_restarts = 0
        self.gave_up = False

    def on_exit(self, returncode: int, now: float) -> Decision:
        """Decide what to do after the process exited with ``returncode`` (negative: killed by signal)."""
        spec = self.spec
        if spec.restart == "never":
            return Decision(False, reason="restart policy 'never'")
        if spec.restart == "on-failure" and returncode == 0:
            return Decision(False, reason="exited cleanly")
        while self._restarts and now - self._restarts[0] > spec.window_s:
            self._restarts.popleft()
        if len(self._restarts) >= spec.max_restarts:
            self.gave_up = True
            return Decision(False, reason=f"{len(self._restarts)} restarts within {spec.window_s:g} s (max {spec.max_restarts}): giving up")
        delay = min(spec.backoff_s * 2 ** len(self._restarts), spec.backoff_max_s)
        self._restarts.append(now + delay)
        self.total_restarts += 1
        return Decision(True, delay, f"restart {len(self._restarts)}/{spec.max_restarts} in window")


def describe_exit(returncode: int) -> str:
    if returncode < 0:
        try:
            return f"killed by {signal.Signals(-returncode).name}"
        except ValueError:
            return f"killed by signal {-returncode}"
    return f"exit code {returncode}"


def validate(cfg: SupervisorConfig, known_commands: dict[str, object] | None = None) -> None:
    """Raise ConfigError for an unusable service list (names, argv, limits; the loader checked the enumerations)."""
    if not 0 <= cfg.malloc_mmap_threshold_mb <= 32 or cfg.malloc_trim_threshold_mb < 0:
        raise ConfigError("supervisor.malloc_mmap_threshold_mb must be 0..32 MiB (glibc ignores larger ones) and "
                          f"malloc_trim_threshold_mb >= 0, got {cfg.malloc_mmap_threshold_mb} and "
                          f"{cfg.malloc_trim_threshold_mb}")
    if not 0 <= cfg.realtime_priority <= 99:
        raise ConfigError(f"supervisor.realtime_priority: must be 0..99, got {cfg.realtime_priority}")
    seen = set()
    for i, spec in enumerate(cfg.services):
        where = f"supervisor.services[{i}]"
        if not spec.name or spec.name in seen or spec.name == "router":
            raise ConfigError(f"{where}.name: must be non-empty, unique and not 'router', got {spec.name!r}")
        seen.add(spec.name)
        if not spec.argv:
            raise ConfigError(f"{where}.argv: empty; give the sigmaslam subcommand and its arguments")
        if spec.enabled and spec.argv[0] == "odometry":  # configs written between stops 26 and 33
            raise ConfigError(f"{where}: 'odometry' is no longer a process: the per-frame fast path runs in the "
                              "frontend's process ('sigmaslam frontend' publishes estimator/state); remove this entry")
        if known_commands is not None and spec.enabled and spec.argv[0] not in known_commands:
            raise ConfigError(f"{where}.argv[0]: {spec.argv[0]!r} is not a sigmaslam subcommand ({sorted(known_commands)})")
        if spec.nice is not None and not -20 <= spec.nice <= 19:
            raise ConfigError(f"{where}.nice: must be -20..19, got {spec.nice}")
        if spec.stop_timeout_s is not None and not spec.stop_timeout_s >= 0:
            raise ConfigError(f"{where}.stop_timeout_s: must be >= 0 s, got {spec.stop_timeout_s}")
        if spec.max_restarts < 0 or spec.window_s <= 0 or spec.backoff_s < 0:
            raise ConfigError(f"{where}: max_restarts >= 0, window_s > 0 and backoff_s >= 0 required")


# ----------------------------------------------------------------------------- processes

def _child_setup(parent_pid: int, nice: int = 0, sched: str = "normal", own_group: bool = False,
                 rt_priority: int = 0) -> None:
    """preexec_fn: give the child the nice ``nice`` (resolved by the supervisor:
    :func:`services.app.scheduling.resolve_nice`) and scheduling class ``sched`` ('fifo' at ``rt_priority``:
    :func:`~services.app.scheduling.resolve_sched`), and with ``own_group`` (it is in a session of its own) its
    scheduling group the same nice (Linux); SIGTERM it when the supervisor dies (Linux prctl PR_SET_PDEATHSIG)."""
    if sys.platform.startswith("linux"):
        apply_in_child(nice, sched, own_group, rt_priority)
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        PR_SET_PDEATHSIG = 1
        libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0)
        if os.getppid() != parent_pid:  # the supervisor died before prctl took effect
            os._exit(1)


class Child:
    """One supervised service: its spec, current process and restart bookkeeping."""

    def __init__(self, spec: ServiceSpec, argv: list[str]) -> None:
        self.spec = spec
        self.argv = argv
        self.tracker = RestartTracker(spec)
        self.proc: subprocess.Popen | None = None
        self.restart_at: float | None = None  # monotonic time of a scheduled restart
        self.done = False  # exited and will not be restarted

    @property
    def pid(self) -> int | None:
        return self.proc.pid if self.proc is not None and self.proc.poll() is None else None


class Supervisor:
    """Starts, watches, restarts and stops the children. ``run()`` returns the exit status."""

    def __init__(self, cfg: SupervisorConfig, config_path: Path, run_dir: Path) -> None:
        cfg = dataclasses.replace(cfg, services=tuple(with_defaults(s) for s in cfg.services))
        self.cfg = cfg
        self.config_path = Path(config_path)
        self.run_dir = Path(run_dir)
        self.stop_requested = False
        self.children: list[Child] = []
        self.router: Child | None = None
        if cfg.start_router:
            # the router carries every message, the path to a pose's among them: it ranks with the frontend
            self.router = Child(with_defaults(ServiceSpec(name="router", argv=("router",), restart="always",
                                                          max_restarts=5, window_s=60.0, backoff_s=0.2, nice=-10)),
                                self._argv(["router"]))
        self.children = [Child(s, self._argv(s.argv)) for s in cfg.services if s.enabled]

    def _argv(self, argv: list[str]) -> list[str]:
        return [sys.executable, "-m", "services.app.cli", argv[0], str(self.config_path), *argv[1:]]

    def _env(self) -> dict[str, str]:
        env = dict(os.environ)
        env["SIGMASLAM_CONFIG"] = str(self.config_path)
        env["SIGMASLAM_RUN_DIR"] = str(self.run_dir)
        env["PYTHONUNBUFFERED"] = "1"
        for name, mb in (("MALLOC_MMAP_THRESHOLD_", self.cfg.malloc_mmap_threshold_mb),
                         ("MALLOC_TRIM_THRESHOLD_", self.cfg.malloc_trim_threshold_mb)):
            if mb > 0 and name not in env:  # glibc reads these when the process starts
                env[name] = str(int(mb) * 1024 * 1024)
        return env

    def _start(self, child: Child) -> None:
        parent = os.getpid()
        env = self._env()
        env[RESTARTS_ENV] = str(child.tracker.total_restarts)  # > 0: a restart (the back end reports 'reset')
        # a process group of its own (a terminal's Ctrl-C reaches only the supervisor, which stops the children in
        # order; killpg stops a child's own children); the path to a pose (asked for nice < 0) in a session of its
        # own, so a scheduler autogroup of its own (Linux) with its nice, the others in the supervisor's group,
        # ranked there by their nice (services/app/scheduling.py)
        own = (child.spec.nice or 0) < 0
        nice, sched, rt, why = resolve_scheduling(child.spec.nice or 0, child.spec.sched, self.cfg.realtime_priority)
        child.proc = subprocess.Popen(child.argv, env=env, start_new_session=own, process_group=None if own else 0,
                                      preexec_fn=lambda: _child_setup(parent, nice, sched, own, rt))
        child.restart_at = None
        self._status(child, f"started pid {child.proc.pid}, nice {nice}" + (f", real-time priority {rt}" if rt else "")
                     + (f" ({why})" if why else ""))

    def _status(self, child: Child, text: str) -> None:
        line = f"[sigmaslam up] {child.spec.name}: {text}"
        print(line, flush=True)
        log.debug(line)

    def _all(self) -> list[Child]:
        return ([self.router] if self.router else []) + self.children

    def request_stop(self, signum: int | None = None, _frame: object = None) -> None:
        self.stop_requested = True

    def _check(self, child: Child, now: float) -> None:
        if child.proc is None or child.done:
            return
        rc = child.proc.poll()
        if rc is None or child.restart_at is not None:
            return
        decision = child.tracker.on_exit(rc, now)
        if decision.restart and not self.stop_requested:
            child.restart_at = now + decision.delay_s
            self._status(child, f"pid {child.proc.pid} {describe_exit(rc)}; restarting in {decision.delay_s:.2f} s ({decision.reason})")
        else:
            child.done = True
            self._status(child, f"pid {child.proc.pid} {describe_exit(rc)}; not restarted ({decision.reason})")
            if child.tracker.gave_up:
                log.error("%s: %s", child.spec.name, decision.reason)

    def run(self) -> int:
        """Run until a stop is requested or every service is done; returns 0, or 1 if a service was given up on."""
        if self.router is not None:
            self._start(self.router)
            deadline = time.monotonic() + self.cfg.router_startup_s
            while time.monotonic() < deadline and not self.stop_requested:
                time.sleep(0.02)
        for child in self.children:
            if not self.stop_requested:
                self._start(child)
        while not self.stop_requested:
            now = time.monotonic()
            for child in self._all():
                self._check(child, now)
                if child.restart_at is not None and now >= child.restart_at:
                    self._start(child)
            if self.children and all(c.done for c in self.children):
                break
            time.sleep(self.cfg.poll_period_s)
        self.shutdown()
        return 1 if any(c.tracker.gave_up for c in self._all()) else 0

    def shutdown(self) -> None:
        """SIGTERM the services, SIGKILL those left after the timeout; then the same for the router."""
        self._stop_group(self.children)
        if self.router is not None:
            self._stop_group([self.router])

    def _stop_group(self, group: list[Child]) -> None:
        live = [c for c in group if c.proc is not None and c.proc.poll() is None]
        for c in group:
            c.restart_at = None
        for c in live:
            _signal_group(c.proc, signal.SIGTERM)
        t0 = time.monotonic()
        waiting = list(live)
        while waiting:
            for c in list(waiting):
                if c.proc.poll() is not None:
                    _signal_group(c.proc, signal.SIGKILL)  # leftovers of its process group, if any
                    waiting.remove(c)
                elif time.monotonic() - t0 >= (limit := self.cfg.stop_limit_s(c.spec)):
                    self._status(c, f"pid {c.proc.pid} still running after {limit:g} s: its stacks, then SIGKILL")
                    _dump_stacks(c.proc)
                    _signal_group(c.proc, signal.SIGKILL)
                    c.proc.wait()
                    waiting.remove(c)
            time.sleep(0.02 if waiting else 0.0)
        for c in live:
            c.done = True
            self._status(c, f"pid {c.proc.pid} stopped ({describe_exit(c.proc.returncode)})")


def _dump_stacks(proc: subprocess.Popen, wait_s: float = 0.5) -> None:
    """Ask a process that did not stop for the stacks of its threads (services/app/process_cmd.py: STACKS_SIGNAL,
    written to its stderr, which is the supervisor's log) and give it ``wait_s`` to write them."""
    from services.app.process_cmd import STACKS_SIGNAL

    try:
        os.kill(proc.pid, STACKS_SIGNAL)
    except (ProcessLookupError, PermissionError):
        return
    try:
        proc.wait(wait_s)
    except subprocess.TimeoutExpired:
        pass


def _signal_group(proc: subprocess.Popen, sig: int) -> None:
    """Signal the child's whole process group (it is the group leader)."""
    try:
        os.killpg(proc.pid, sig)
    except (ProcessLookupError, PermissionError):
        pass
