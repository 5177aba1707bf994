"""The player: its declared topics and its description. Its loop is services/player/playback.py: a source paced by
the sensor clock (the estimator's states in lockstep, or a rate), not driven by a runner."""

from __future__ import annotations

import argparse

from shared import topics
from shared.dataflow import Input, ProcessNode
from shared.process_description import ProcessDescription, Scheduling


class PlayerNode(ProcessNode):
    name = "player"
    inputs = (
        Input(topics.CONTROL, "on_control", note="pause, resume, stop"),
        Input(topics.STATE, "on_state", policy="latest", depth=64, when="--lockstep",
              note="the next frame after this one's state"),
        Input(topics.HEARTBEAT, "on_heartbeat", policy="all", depth=1000, when="--wait-for",
              note="the services are up before playing"),
    )
    outputs = (topics.IMU, topics.FRAME, topics.STREAM_END)
    output_notes = {topics.STREAM_END.key: "once, after the last frame"}


def _arguments(p: argparse.ArgumentParser) -> None:
    from services.player.playback import add_arguments

    add_arguments(p)


def _play(cfg, args: argparse.Namespace) -> int:
    from services.player.playback import play

    return play(cfg, args)


DESCRIPTION = ProcessDescription(
    name="player", node=PlayerNode, main=_play, arguments=_arguments, config_positional=False,
    scheduling=Scheduling(nice=-10, sched="fifo"),  # the sensor input: the path to a pose starts here (real-time where allowed)
    help="replay an EuRoC ASL folder or an MCAP recording onto the sensor topics (--lockstep, --realtime, --rate)")
