"""The process declarations are the one description of the pipeline's dataflow: docs/architecture.md's graph is
generated from them, every process package has one, and no node reads or writes a topic it does not declare."""

from __future__ import annotations

from pathlib import Path

import pytest

from services.app.processes import DOC, PROCESS_NODES, graph_block
from services.backend.node import BackendNode
from services.depth.node import DepthNode
from services.frontend.node import FrontendNode
from services.mapping.node import MappingNode
from shared import topics
from shared.dataflow import Emit, Input, ProcessNode, UndeclaredTopic, graph
from shared.messages import Header, StreamEnd

SERVICES = Path(__file__).resolve().parents[1] / "services"
RUNNER_DRIVEN = (FrontendNode, BackendNode, DepthNode, MappingNode)


def test_the_page_shows_the_declared_graph():
    assert graph_block() in DOC.read_text(), (
        "docs/architecture.md's topic graph differs from the node declarations: "
        "run `python -m services.app.processes --write`")


def test_every_process_package_declares_its_node():
    packages = sorted(p.name for p in SERVICES.iterdir() if (p / "service.py").is_file())
    # every process package declares its node
    assert sorted({n.__module__.split(".")[1] for n in PROCESS_NODES}) == packages
    names = [n.name for n in PROCESS_NODES]
    assert len(set(names)) == len(names)
    for n in PROCESS_NODES:
        assert sum(i.role == "trigger" for i in n.inputs) <= 1, n.name
        for inp in n.inputs:
            assert inp.topic in topics.ALL, (n.name, inp.topic.key)
    for n in RUNNER_DRIVEN:  # the runners call these handlers
        for inp in n.inputs:
            assert callable(getattr(n, inp.handler, None)), f"{n.name}: no handler {inp.handler}"
        assert set(n.outputs) <= set(topics.ALL)


def test_every_topic_is_produced_and_consumed():
    g = graph(PROCESS_NODES)
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
