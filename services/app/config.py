"""The application's config section: what ``sigmaslam up`` starts and how it restarts and stops it
(:class:`SupervisorConfig`, one :class:`ServiceSpec` per process). A schema module like every ``config.py``:
:mod:`services.app.system_config` composes it, the supervisor (:mod:`services.app.supervisor`) runs it."""

from __future__ import annotations

import dataclasses
from typing import Literal

from shared.config import param

@dataclasses.dataclass(frozen=True)
class ServiceSpec:
    """One service process of the deployment."""

    name: str = param("", "name used in logs and status lines")
    argv: tuple[str, ...] = param((), "the 'sigmaslam ...' arguments, subcommand first, e.g. ['record', '--out', 'run.mcap']")
    enabled: bool = param(True, "start this service")
    restart: Literal["on-failure", "always", "never"] = param("on-failure", "when to restart: 'on-failure' (exit code != 0 or a signal), 'always' or 'never'")
    max_restarts: int = param(3, "restarts allowed within window_s before the supervisor gives up on the service")
    window_s: float = param(60.0, "sliding window over which restarts are counted", "s")
    backoff_s: float = param(0.5, "delay before the first restart in the window; doubles with each further one", "s")
    backoff_max_s: float = param(10.0, "longest delay before a restart", "s")
    nice: int | None = param(None, "OS scheduling niceness added to the process and given to its scheduling group "
                             "(-20..19; below the supervisor's own needs CAP_SYS_NICE or a nice limit, else the "
                             "lowest allowed is used and the supervisor says so); e.g. 19 for depth and mapping so "
                             "that, on a loaded CPU, the path to a pose gets the cores first (null: the process's "
                             "default, its description's scheduling: frontend, back end, player and router -10, "
                             "depth and mapping 19, recorder 10)")
    sched: Literal["default", "normal", "batch", "idle", "fifo"] = param(
        "default", "Linux scheduling class of the process: 'idle' (SCHED_IDLE) runs it only on CPU time no normal "
        "process wants, so that on two cores depth, mapping and the viewer never delay a pose; 'batch' (SCHED_BATCH) "
        "is for long computations; 'fifo' (SCHED_FIFO at supervisor.realtime_priority) runs it the moment it has "
        "work, ahead of every normal process: the frontend's per-frame work and the sensor input (where real-time scheduling is not "
        "allowed, the process runs at its nice and the supervisor says so); 'default': the process's own (its "
        "description's scheduling); ignored elsewhere than Linux")
    stop_timeout_s: float | None = param(None, "after SIGTERM, SIGKILL this service if still alive after this long "
                                         "(0: the supervisor's shutdown_timeout_s; null: the process's default, 60 s "
                                         "for the mapping, which meshes and writes its map when stopped)", "s")


@dataclasses.dataclass(frozen=True)
class SupervisorConfig:
    """What ``sigmaslam up`` starts and how it restarts and stops it."""

    services: tuple[ServiceSpec, ...] = param((), "service processes to run (each its own OS process)")
    start_router: bool = param(True, "start 'sigmaslam router' before the services (and stop it last)")
    router_startup_s: float = param(0.5, "wait after starting the router before starting the services", "s")
    shutdown_timeout_s: float = param(5.0, "after SIGTERM, children still alive after this long are SIGKILLed", "s")
    realtime_priority: int = param(10, "SCHED_FIFO priority (1-99) of the services whose class is 'fifo' (the "
                                   "frontend and the sensor input: player, ros2_input); 0: none runs real-time, each runs at its nice instead. A real-time "
                                   "process that never blocked would keep its core (the kernel leaves others 5 %: "
                                   "sched_rt_runtime_us); the frontend blocks between frames (docs/reliability.md)")
    run_dir: str = param("runs", "parent folder of each run's folder (resolved config, outputs)")
    poll_period_s: float = param(0.05, "how often the supervisor checks its children", "s")
    malloc_mmap_threshold_mb: int = param(
        32, "each service's glibc malloc takes blocks up to this size from its heap, not from fresh pages "
        "(MALLOC_MMAP_THRESHOLD_; 32 is glibc's largest): fresh pages fault on first touch, and a frame's images and "
        "a network's temporaries are such blocks (the depth network: 40 -> 32 ms per frame). 0: glibc's default; a "
        "value already in the environment wins", "MiB")
    malloc_trim_threshold_mb: int = param(
        256, "free heap a service keeps for reuse before giving it back to the OS (MALLOC_TRIM_THRESHOLD_; 0: glibc's "
        "default; a value already in the environment wins)", "MiB")

    def stop_limit_s(self, spec: ServiceSpec) -> float:
        """How long ``spec``'s process may take to stop after SIGTERM before it is SIGKILLed."""
        return spec.stop_timeout_s if spec.stop_timeout_s else self.shutdown_timeout_s

    def longest_stop_s(self) -> float:
        """The longest any service may take to stop after SIGTERM."""
        return max([self.shutdown_timeout_s, *(self.stop_limit_s(s) for s in self.services)])
