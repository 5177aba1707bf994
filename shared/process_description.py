"""How a process describes itself, once: the ``DESCRIPTION`` at the end of its package's ``node.py``.

A :class:`ProcessDescription` says what the application needs to run the process and draw it: its name (that of
its node, its heartbeat and its command), its declared node (the topics it reads and writes), how its node is built
from the system config (:attr:`ProcessDescription.build`, the process's composition root: what the node is made of
is imported there, so that reading the descriptions stays cheap) or, for a process with a loop of its own (the
player, the recorder), its :attr:`ProcessDescription.main`; what it does before joining the bus (warm-up), whether it
writes an output (``--out``), its scheduling defaults under the supervisor, and whether ``sigmaslam run`` starts it
when the config names no pipeline process. The application's registry (services/app/processes.py) lists the
descriptions and derives from them the CLI's process commands, the in-process pipeline, the supervisor's defaults and
the topic graph.
"""

from __future__ import annotations

import argparse
import dataclasses
from typing import Any, Callable, Literal

from shared.dataflow import ProcessNode


class ProcessStartError(RuntimeError):
    """A process that cannot start (bad calibration, missing weights, a port in use): it exits with ``code`` and the
    message before it joins the bus."""

    def __init__(self, message: str, code: int = 2) -> None:
        super().__init__(message)
        self.code = code


@dataclasses.dataclass(frozen=True)
class Scheduling:
    """How the supervisor runs the process unless its ``supervisor.services`` entry says otherwise."""

    nice: int = 0  # niceness added to the process and its scheduling group (-20..19; below 0 where allowed)
    sched: Literal["normal", "batch", "idle", "fifo"] = "normal"  # Linux scheduling class ('fifo': real-time)
    stop_timeout_s: float = 0.0  # SIGKILL after SIGTERM after this long [s] (0: supervisor.shutdown_timeout_s)


@dataclasses.dataclass(frozen=True)
class Output:
    """What the process writes when given ``--out``."""

    in_run: str  # where ``sigmaslam run`` puts it in its run folder: '' the folder itself, else a file name there
    help: str  # the ``--out`` option's help


@dataclasses.dataclass(frozen=True)
class Start:
    """How a process is being started: what its build gets besides the system config."""

    out_dir: str | None = None  # --out (a folder or a file); None: the configured one, '': write nothing
    restarts: int = 0  # how often the supervisor restarted it (0: its first life, or not supervised)
    clock: Callable[[], float] | None = None  # the in-process runner's sensor clock [s]; None: the wall clock
    cameras: list | None = None  # the rig, already loaded (in process); None: load it from the config's rig section

    def rig(self, cfg) -> list:
        """The rig's cameras: :attr:`cameras`, else loaded from ``cfg.rig`` (a calibration that cannot be read is a
        :class:`ProcessStartError`)."""
        if self.cameras is not None:
            return self.cameras
        from shared.camera import CalibrationError
        from shared.rig import load_rig_config

        try:
            return load_rig_config(cfg.rig)
        except (CalibrationError, FileNotFoundError) as exc:
            raise ProcessStartError(str(exc)) from exc


@dataclasses.dataclass(frozen=True)
class ProcessDescription:
    """One process of sigmaslam (see the module's docstring); exactly one of ``build`` and ``main``."""

    name: str  # its node's name: heartbeat/<name>, stats/<name>, logs
    node: type[ProcessNode]  # its declared inputs and outputs
    help: str  # one line for ``sigmaslam --help``
    command: str = ""  # its ``sigmaslam`` command when it differs from the name
    # (system config, start) -> the node, run by transport.runner.run_node; may raise ProcessStartError
    build: Callable[[Any, Start], ProcessNode] | None = None
    # (system config, parsed arguments) -> exit status: a process with a loop of its own
    main: Callable[[Any, argparse.Namespace], int] | None = None
    warm_up: Callable[[ProcessNode], None] | None = None  # before the first heartbeat (players wait for it)
    ready: Callable[[ProcessNode, Any], str] | None = None  # the line printed once it runs (node, system config)
    arguments: Callable[[argparse.ArgumentParser], None] | None = None  # its own command-line arguments
    config_positional: bool = True  # CONFIG is the first positional argument (else its arguments place it)
    output: Output | None = None  # what --out writes (None: no --out)
    scheduling: Scheduling = Scheduling()
    default_pipeline: bool = False  # started by ``sigmaslam run`` when the config names no pipeline process
    # a boolean field of the system config ('ros2.enabled') that, when true, starts the process beside the configured
    # ones (``sigmaslam run``, ``up``, ``demo``); empty: started only when supervisor.services names it
    switch: str = ""
    in_process: bool = False  # one of the nodes the in-process runner can drive (services/app/inprocess.py)

    def __post_init__(self) -> None:
        if (self.build is None) == (self.main is None):
            raise ValueError(f"process {self.name!r}: give exactly one of build and main")

    @property
    def cli_command(self) -> str:
        """Its ``sigmaslam`` command."""
        return self.command or self.name
