"""The recorder: its declared topics (every topic of the namespace: one wildcard subscription, raw bytes to MCAP)
and its description. Its loop is services/recorder/recording.py."""

from __future__ import annotations

import argparse

from shared import topics
from shared.dataflow import Input, ProcessNode
from shared.process_description import Output, ProcessDescription, Scheduling


class RecorderNode(ProcessNode):
    name = "recorder"
    inputs = tuple(Input(t, "on_sample", policy="all") for t in topics.ALL)
    outputs = ()


def _arguments(p: argparse.ArgumentParser) -> None:
    from services.recorder.recording import add_arguments

    add_arguments(p)


def _record(cfg, args: argparse.Namespace) -> int:
    from services.recorder.recording import record

    return record(cfg, args)


DESCRIPTION = ProcessDescription(
    name="recorder", command="record", node=RecorderNode, main=_record, arguments=_arguments,
    scheduling=Scheduling(nice=10),  # after the pipeline; writes what it has queued when stopped
    output=Output(in_run="recording.mcap",
                  help="output file FILE.mcap (default: <recorder.output_dir>/sigmaslam-<UTC>-<pid>.mcap)"),
    help="record topics to MCAP (with Foxglove mirrors); --recover a cut file")
