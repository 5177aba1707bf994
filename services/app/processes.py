"""The processes of sigmaslam, a line each: the registry everything the application knows about processes derives
from.

Each process describes itself once, at the end of its package's node.py (``DESCRIPTION``, a
:class:`shared.process_description.ProcessDescription`: name, declared node, how its node is built from the system
config, warm-up, output, scheduling defaults). From :data:`PROCESSES` the application derives:

- the ``sigmaslam <process>`` commands (services/app/cli.py; one generic entry, services/app/process_cmd.py);
- the in-process pipeline (services/app/inprocess.py: :func:`in_process_nodes`);
- what ``sigmaslam run`` starts when the config names no pipeline process, the name each process's heartbeat
  carries, and the supervisor's per-process defaults (:func:`default_pipeline`, :func:`heartbeat_name`,
  :func:`with_defaults`);
- the topic graph of docs/architecture.md (services/app/topic_graph.py).

Adding a process: its package with a node.py that ends in a ``DESCRIPTION``, and its line in :data:`PROCESSES`;
tests/test_architecture_graph.py fails when a declaration and what runs disagree.
"""

from __future__ import annotations

import dataclasses

from services.app.config import ServiceSpec
from services.backend.node import DESCRIPTION as BACKEND
from services.depth.node import DESCRIPTION as DEPTH
from services.frontend.node import DESCRIPTION as FRONTEND
from services.mapping.node import DESCRIPTION as MAPPING
from services.player.node import DESCRIPTION as PLAYER
from services.recorder.node import DESCRIPTION as RECORDER
from services.ros2.node import DESCRIPTION as ROS2
from services.ros2_input.node import DESCRIPTION as ROS2_INPUT
from services.viewer.node import DESCRIPTION as VIEWER
from shared.process_description import ProcessDescription, Start

# one line per process; the in-process pipeline runs its nodes in this order (the frontend's fast path before the
# back end: a keyframe's state comes from the previous window, as in a live run)
PROCESSES: tuple[ProcessDescription, ...] = (PLAYER, FRONTEND, BACKEND, DEPTH, MAPPING, VIEWER, RECORDER, ROS2,
                                              ROS2_INPUT)


def by_command(command: str) -> ProcessDescription | None:
    """The process whose ``sigmaslam`` command is ``command`` (None: not a process command)."""
    return next((d for d in PROCESSES if d.cli_command == command), None)


def heartbeat_name(command: str) -> str:
    """The name the heartbeat of the process started by ``sigmaslam <command>`` carries."""
    d = by_command(command)
    return command if d is None else d.name


def default_pipeline() -> list[ServiceSpec]:
    """What ``sigmaslam run`` starts when ``supervisor.services`` names no pipeline process."""
    return [ServiceSpec(name=d.name, argv=(d.cli_command,)) for d in PROCESSES if d.default_pipeline]


def switched_on(cfg, services) -> list[ServiceSpec]:
    """The processes whose config switch (their description's ``switch``, e.g. ``ros2.enabled``) is on in ``cfg`` and
    that ``services`` (ServiceSpec entries) does not start already: what ``run``, ``up`` and ``demo`` add."""
    started = {s.argv[0] for s in services if s.argv and s.enabled}
    out = []
    for d in PROCESSES:
        value = cfg
        for part in d.switch.split(".") if d.switch else ():
            value = getattr(value, part)
        if d.switch and value is True and d.cli_command not in started:
            out.append(ServiceSpec(name=d.name, argv=(d.cli_command,)))
    return out


def with_defaults(spec: ServiceSpec) -> ServiceSpec:
    """``spec`` with the scheduling it leaves unset (None, 'default') taken from its process's description."""
    d = by_command(spec.argv[0]) if spec.argv else None
    s = d.scheduling if d is not None else None
    return dataclasses.replace(
        spec, nice=spec.nice if spec.nice is not None else (s.nice if s else 0),
        sched=spec.sched if spec.sched != "default" else (s.sched if s else "normal"),
        stop_timeout_s=spec.stop_timeout_s if spec.stop_timeout_s is not None else (s.stop_timeout_s if s else 0.0))


def in_process_nodes(cfg, names: list[str], start: Start) -> dict:
    """name -> node of the in-process processes named (in registry order), each built by its description."""
    unknown = set(names) - {d.name for d in PROCESSES if d.in_process}
    if unknown:
        raise ValueError(f"not processes the in-process runner drives: {sorted(unknown)}")
    return {d.name: d.build(cfg, start) for d in PROCESSES if d.name in names}
