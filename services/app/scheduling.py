"""How the supervisor ranks its children on the CPU against each other and against the other programs of the machine.

Linux's autogroup scheduler (``kernel.sched_autogroup_enabled``, on in most distributions) makes each session a
scheduling group, and between groups only the group's nice counts (``/proc/<pid>/autogroup``), whatever the nice of
the tasks inside. In one group the whole pipeline would be a single peer of each busy process another program runs:
with two of them on two cores it lost most frames (docs/benchmarks.md). So the supervisor starts

- the path to a pose (router, player, frontend, back end: processes asked to run at a nice below 0) each in a
  session of its own, a scheduling group whose nice is the process's: ahead of other programs where a negative nice
  is allowed, their peer where it is not;
- the others (depth and mapping at nice 19, the viewer SCHED_IDLE, the recorder at nice 10) in its own group, where
  they yield to the supervisor's own threads and to each other by their nice, and which as a whole is a peer of the
  other programs: under load they slow down and skip frames (counted), but are not starved outright.

The frontend, whose per-frame work is the pose's latency, and the sensor input (player, ros2_input) run real-time
(SCHED_FIFO at ``supervisor.realtime_priority``, all three at the same priority, so none preempts another) where that
is allowed: a real-time task runs the moment a frame wakes it, ahead of every normal task, whatever their nice or
group, and is preempted by none of them. Nice alone left the frontend waiting for a core behind the back end's
optimisations and the depth network: its tracking took 12 ms of CPU at the 99th percentile but 35-60 ms of wall
time, and the player put frames up to 30 ms late (docs/benchmarks.md). They block between frames (the frontend about
half a core at 20 Hz, the player a sixth), so the rest of the pipeline keeps the remainder; a real-time task that
never blocked would keep its core, less the 5 % the kernel's throttling (``sched_rt_runtime_us``) leaves to others. Where real-time scheduling is not allowed (no
CAP_SYS_NICE and no ``ulimit -r``), :func:`resolve_sched` falls back to the normal class and its nice and says so.

Where autogroups are off, or inside a container's cgroup, the same nice values rank the tasks directly. A nice below
0 needs CAP_SYS_NICE (root, ``setcap``, compose's ``cap_add: [SYS_NICE]``) or a nice limit (``ulimit -e``,
limits.conf ``nice``); without either the child runs at the lowest nice allowed, which :func:`resolve_nice` reports so
that the supervisor can say so.
"""

from __future__ import annotations

import errno
import os
import resource
import time

CAP_SYS_NICE = 23  # linux/capability.h
AUTOGROUP = "/proc/self/autogroup"


def has_cap_sys_nice(status_path: str = "/proc/self/status") -> bool:
    """Whether this process holds CAP_SYS_NICE in its effective set (Linux; False where that cannot be read)."""
    try:
        with open(status_path) as f:
            for line in f:
                if line.startswith("CapEff:"):
                    return bool(int(line.split()[1], 16) >> CAP_SYS_NICE & 1)
    except (OSError, ValueError, IndexError):
        pass
    return False


def lowest_nice() -> int:
    """The lowest nice this process may give itself or its children (-20 with CAP_SYS_NICE; else what RLIMIT_NICE
    allows, 20 - limit; never above the current nice, which a process may always keep)."""
    current = os.getpriority(os.PRIO_PROCESS, 0)
    if has_cap_sys_nice():
        return -20
    soft = resource.getrlimit(resource.RLIMIT_NICE)[0] if hasattr(resource, "RLIMIT_NICE") else 0
    if soft == resource.RLIM_INFINITY:
        return -20
    return max(-20, min(current, 20 - int(soft)))


def resolve_nice(added: int, base: int | None = None, lowest: int | None = None) -> tuple[int, str]:
    """(the nice a child gets, '' or why it is not the one asked for): ``base`` (default: this process's nice) plus
    ``added``, within -20..19 and not below ``lowest`` (default: :func:`lowest_nice`)."""
    base = os.getpriority(os.PRIO_PROCESS, 0) if base is None else base
    lowest = lowest_nice() if lowest is None else lowest
    wanted = max(-20, min(19, base + added))
    if wanted >= lowest:
        return wanted, ""
    return lowest, (f"nice {wanted} is not permitted here, so nice {lowest}: a peer of other programs' busy "
                    f"processes, not ahead of them; allow it with CAP_SYS_NICE or `ulimit -e {20 - wanted}`")


def highest_rt_priority() -> int:
    """The highest SCHED_FIFO priority this process may give its children (99 with CAP_SYS_NICE; else the soft
    RLIMIT_RTPRIO, 0 where none is allowed)."""
    if not hasattr(os, "SCHED_FIFO"):
        return 0
    if has_cap_sys_nice():
        return 99
    soft = resource.getrlimit(resource.RLIMIT_RTPRIO)[0] if hasattr(resource, "RLIMIT_RTPRIO") else 0
    return 99 if soft == resource.RLIM_INFINITY else max(0, min(99, int(soft)))


def resolve_sched(sched: str, priority: int, highest: int | None = None) -> tuple[str, int, str]:
    """(class, real-time priority, '' or why not the one asked for) a child gets for ``sched`` ('fifo' at
    ``priority``; the others at 0): 'fifo' where ``priority`` > 0 and allowed (``highest``, default
    :func:`highest_rt_priority`), else 'normal'."""
    if sched != "fifo":
        return sched, 0, ""
    if priority <= 0:
        return "normal", 0, "supervisor.realtime_priority is 0: not real-time, at its nice"
    highest = highest_rt_priority() if highest is None else highest
    if priority <= highest:
        return "fifo", priority, ""
    return "normal", 0, (f"real-time priority {priority} is not permitted here, so the normal class at its nice: "
                         f"allow it with CAP_SYS_NICE or `ulimit -r {priority}`")


def resolve_scheduling(added_nice: int, sched: str, rt_priority: int) -> tuple[int, str, int, str]:
    """(nice, class, real-time priority, '' or why not what was asked) of a child asked for ``added_nice`` and
    ``sched`` (:func:`resolve_nice`, :func:`resolve_sched`): what :func:`apply_in_child` takes."""
    nice, why_nice = resolve_nice(added_nice)
    sched, rt, why_sched = resolve_sched(sched, rt_priority)
    return nice, sched, rt, "; ".join(w for w in (why_nice, why_sched) if w)


def autogroup_nice(path: str = AUTOGROUP) -> int | None:
    """The nice of this process's autogroup, or None where it has none: no such file, autogroups off, or a process
    inside a cgroup of its own (a container, a CI runner), where the kernel prints nothing for it."""
    try:
        with open(path) as f:
            fields = f.read().split()
    except OSError:
        return None
    if len(fields) == 3 and fields[0].startswith("/autogroup-") and fields[1] == "nice":
        try:
            return int(fields[2])
        except ValueError:
            return None
    return None


def set_autogroup_nice(nice: int, path: str = AUTOGROUP, tries: int = 40) -> bool:
    """Give this process's autogroup (its session's scheduling group) ``nice``; False where there is none or it is not
    allowed. The kernel takes at most ten such changes a second from processes without CAP_SYS_ADMIN (EAGAIN): retried."""
    for _ in range(tries):
        try:
            with open(path, "w") as f:
                f.write(str(nice))
            return True
        except OSError as exc:
            if exc.errno != errno.EAGAIN:
                return False
            time.sleep(0.03)
    return False


def apply_in_child(nice: int, sched: str, own_group: bool, rt_priority: int = 0) -> None:
    """In a new child before exec: its nice and scheduling class (``sched`` as :func:`resolve_sched` resolved it;
    'fifo' at ``rt_priority``), and with ``own_group`` (a session of its own already) its scheduling group's nice."""
    try:
        os.setpriority(os.PRIO_PROCESS, 0, nice)
    except PermissionError:  # resolve_nice kept it within what is allowed; a limit lowered since keeps the current
        pass
    policy = {"batch": getattr(os, "SCHED_BATCH", None), "idle": getattr(os, "SCHED_IDLE", None)}.get(sched)
    if policy is not None:
        os.sched_setscheduler(0, policy, os.sched_param(0))
    elif sched == "fifo":  # threads the process starts inherit it (Zenoh's, which deliver its frames, too)
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(rt_priority))
    if own_group:
        set_autogroup_nice(19 if sched == "idle" else nice)  # SCHED_IDLE's counterpart for a group: the lowest weight
