"""The process declarations are the one description of the pipeline's dataflow: docs/architecture.md's graph is
generated from them, every process package describes its process in its node.py, the CLI has one command per
process, and no node (nor ``sigmaslam run``) reads or writes a topic it does not declare."""

from __future__ import annotations

import importlib
from pathlib import Path

import pytest

from services.app.cli import command_names
from services.app.processes import PROCESSES, default_pipeline, with_defaults
from services.app.run_collector import Collection, RunCollectorNode, subscribe
from services.app.topic_graph import DOC, GRAPH_NODES, graph_block
from services.app.config import ServiceSpec
from shared import topics
from shared.dataflow import Emit, Input, ProcessNode, UndeclaredTopic, graph
from shared.messages import Header, StreamEnd

SERVICES = Path(__file__).resolve().parents[1] / "services"
RUNNER_DRIVEN = tuple(d.node for d in PROCESSES if d.build is not None)


def test_the_page_shows_the_declared_graph():
    assert graph_block() in DOC.read_text(), (
        "docs/architecture.md's topic graph differs from the node declarations: "
        "run `python -m services.app.topic_graph --write`")


def test_every_process_package_describes_its_process_in_its_node_module():
    packages = sorted(p.name for p in SERVICES.iterdir() if (p / "node.py").is_file() and p.name != "app")
    assert sorted(d.node.__module__.split(".")[1] for d in PROCESSES) == packages
    for d in PROCESSES:
        assert d.node.__module__.endswith(".node") and importlib.import_module(d.node.__module__).DESCRIPTION is d
    names = [d.name for d in PROCESSES]
    assert len(set(names)) == len(names) and len({d.cli_command for d in PROCESSES}) == len(PROCESSES)
    for n in (d.node for d in PROCESSES):
        assert sum(i.role == "trigger" for i in n.inputs) <= 1, n.name
        for inp in n.inputs:
            assert inp.topic in topics.ALL, (n.name, inp.topic.key)
    for n in RUNNER_DRIVEN:  # the runners call these handlers
        for inp in n.inputs:
            assert callable(getattr(n, inp.handler, None)), f"{n.name}: no handler {inp.handler}"
        assert set(n.outputs) <= set(topics.ALL)


def test_the_cli_and_the_supervisor_take_the_processes_from_the_registry():
    commands = command_names()
    assert all(commands.count(d.cli_command) == 1 for d in PROCESSES)
    assert [s.argv[0] for s in default_pipeline()] == ["frontend", "backend"]
    mapping = with_defaults(ServiceSpec(name="m", argv=("mapping",)))  # unset: the description's scheduling
    assert (mapping.nice, mapping.sched, mapping.stop_timeout_s) == (19, "normal", 60.0)
    assert with_defaults(ServiceSpec(name="m", argv=("mapping",), nice=5, stop_timeout_s=2.0)).stop_timeout_s == 2.0


class _Recorder:
    """A transport node stand-in that records the subscriptions made on it."""

    def __init__(self):
        self.made = []

    def subscriber(self, topic, policy=None, depth=None, handler=None):
        self.made.append((topic.key, policy, depth, handler is not None))
        return object()


def test_the_run_subscribes_what_it_declares():
    """What `sigmaslam run` reads is its declared node's inputs, queue by queue (the graph's `sigmaslam run` edges);
    the transport node refuses anything else (declared=RunCollectorNode)."""
    rec = _Recorder()
    queues = subscribe(rec, Collection())
    assert rec.made == [(i.topic.key, i.policy, i.depth, i.handler.startswith("on_")) for i in RunCollectorNode.inputs]
    assert set(queues) == {"states", "stats", "ends", "finals"}


def test_every_topic_is_produced_and_consumed():
    g = graph(GRAPH_NODES)
    for t in topics.ALL:
        if t in (topics.STATS, topics.HEARTBEAT):
            continue  # every node publishes its own
        assert g[t.key]["publishers"], f"nobody publishes {t.key}"
        assert [s for s in g[t.key]["subscribers"] if s != "recorder"], f"nobody reads {t.key}"


class _Tiny(ProcessNode):
    name = "tiny"
    inputs = (Input(topics.IMU, "on_imu"), Input(topics.FRAME, "on_frame", role="trigger"))
    outputs = (topics.FEATURES,)

    def on_imu(self, msg):
        return [Emit(topics.STATE, msg)]  # not among its outputs

    def on_frame(self, msg):
        return []


def test_a_node_cannot_emit_or_read_what_it_does_not_declare():
    node = _Tiny()
    end = StreamEnd(header=Header(stamp_ns=1, seq=0, frame_id="x"), source="x", frames_sent=0)
    with pytest.raises(UndeclaredTopic, match="estimator/state"):
        node.handle(node.inputs[0], end)
    with pytest.raises(UndeclaredTopic, match="on_map"):
        node.use_inputs(["on_frame", "on_map"])
    node.use_inputs(["on_frame"])
    assert [i.handler for i in node.inputs] == ["on_frame"] and len(_Tiny.inputs) == 2
