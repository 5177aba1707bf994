"""The machine a pipeline bench runs on: the cores it may use (``--cpus``) and the other work beside it (``--load``).

- :func:`parse_cpus` reads a core list as ``taskset -c`` does ("0", "0,1", "0-3,6"); :class:`pinned` restricts this
  process to those cores for a ``with`` block, and every process it starts inherits that (Linux
  ``sched_setaffinity``): the supervisor, router, player, services and the bench's own subscriber.
- :class:`BusyLoad` starts N processes that spin at normal priority (nice 0, SCHED_OTHER) on the same cores, each in
  a session of its own as a separate program is (its own scheduler autogroup where the kernel has them, as an editor
  or a build started from another terminal, or another service of the machine), and stops them when the block ends
  (they also get SIGTERM if the bench dies: PR_SET_PDEATHSIG).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys

# the competing work: a process that only spins (no memory traffic, no system calls)
SPIN = "import signal, sys\nsignal.signal(signal.SIGTERM, lambda *a: sys.exit(0))\nwhile True:\n    pass\n"


def parse_cpus(text: str) -> list[int]:
    """Core numbers of a list such as '0', '0,1', '0-3,6' (sorted, unique); ValueError for anything else or for a
    core this process may not use."""
    cpus: set[int] = set()
    for part in (p.strip() for p in text.split(",")):
        lo, sep, hi = part.partition("-")
        if not lo.isdigit() or (sep and not hi.isdigit()):
            raise ValueError(f"--cpus {text!r}: expected core numbers such as 0 or 0,1 or 0-3")
        first, last = int(lo), int(hi) if sep else int(lo)
        if last < first:
            raise ValueError(f"--cpus {text!r}: range {part} runs backwards")
        cpus.update(range(first, last + 1))
    allowed = available_cpus()
    if not cpus <= allowed:
        raise ValueError(f"--cpus {text!r}: core(s) {sorted(cpus - allowed)} not available here "
                         f"(this process may use {sorted(allowed)})")
    return sorted(cpus)


def available_cpus() -> set[int]:
    """The cores this process may run on (all of os.cpu_count() where affinity is not supported)."""
    if hasattr(os, "sched_getaffinity"):
        return set(os.sched_getaffinity(0))
    return set(range(os.cpu_count() or 1))


class pinned:
    """``with pinned(cpus):`` this process (and what it starts meanwhile) runs on ``cpus`` only; None: unchanged."""

    def __init__(self, cpus: list[int] | None) -> None:
        self.cpus, self._before = cpus, None

    def __enter__(self) -> "pinned":
        if self.cpus is not None:
            if not hasattr(os, "sched_setaffinity"):
                raise OSError("--cpus needs Linux (sched_setaffinity)")
            self._before = os.sched_getaffinity(0)
            os.sched_setaffinity(0, self.cpus)
        return self

    def __exit__(self, *exc) -> None:
        if self._before is not None:
            os.sched_setaffinity(0, self._before)


def _load_child_setup() -> None:
    """preexec_fn of a load process: SIGTERM when the bench dies (Linux)."""
    if sys.platform.startswith("linux"):
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGTERM), 0, 0, 0)  # PR_SET_PDEATHSIG


class BusyLoad:
    """``with BusyLoad(n, cpus):`` n spinning processes at normal priority on ``cpus`` (None: wherever this process
    may run), each in its own session; ``pids`` while they run."""

    def __init__(self, n: int, cpus: list[int] | None = None) -> None:
        if n < 0:
            raise ValueError(f"--load must be >= 0, got {n}")
        self.n, self.cpus = n, cpus
        self.procs: list[subprocess.Popen] = []

    @property
    def pids(self) -> list[int]:
        return [p.pid for p in self.procs]

    def __enter__(self) -> "BusyLoad":
        env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
        for _ in range(self.n):
            p = subprocess.Popen([sys.executable, "-S", "-c", SPIN], env=env, start_new_session=True,
                                 stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, preexec_fn=_load_child_setup)
            self.procs.append(p)
            # normal priority even when the bench itself runs niced (`nice -n 10 python -m tools bench ...`), where
            # that is allowed; the cores given (or all of ours)
            try:
                os.setpriority(os.PRIO_PROCESS, p.pid, 0)
            except PermissionError:
                print(f"[bench load] pid {p.pid} stays at this process's nice {os.getpriority(os.PRIO_PROCESS, 0)} "
                      "(nice 0 needs CAP_SYS_NICE): the load is lighter than normal work", flush=True)
            if self.cpus is not None:
                os.sched_setaffinity(p.pid, self.cpus)
        return self

    def __exit__(self, *exc) -> None:
        for p in self.procs:
            if p.poll() is None:
                p.terminate()
        for p in self.procs:
            try:
                p.wait(timeout=5)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        self.procs = []
