from dataclasses import dataclass

from shared.backlog import shed_backlog
from transport.queues import BoundedQueue


@dataclass
class F:
    seq: int
    is_keyframe: bool = False


def test_keeps_newest_and_every_keyframe_in_order():
    frames = [F(i, is_keyframe=i in (1, 4)) for i in range(10)]
    kept, skipped = shed_backlog(frames, 3)
    assert [f.seq for f in kept] == [1, 4, 7, 8, 9]
    assert skipped == 5


def test_no_skipping_within_the_bound_or_when_disabled():
    frames = [F(i) for i in range(4)]
    assert shed_backlog(frames, 4) == (frames, 0)
    assert shed_backlog(frames * 5, 0) == (frames * 5, 0)


def test_shed_items_count_as_drops_not_as_new_arrivals():
    q = BoundedQueue("all", 64, "frontend/frame")
    for i in range(6):
        q.put(F(i))
    kept, skipped = shed_backlog(q.drain(), 2)
    q.count_shed(skipped)
    assert q.counters()[:2] == (6, 4)


def test_a_backlog_of_keyframes_keeps_only_the_newest():
    frames = [F(i, is_keyframe=i % 2 == 0) for i in range(12)]  # keyframes 0, 2, ..., 10
    kept, skipped = shed_backlog(frames, 3, max_keyframes=3)
    # the newest 3 frames (9, 10, 11) hold keyframe 10; of the older keyframes the newest 2 stay: 3 in all
    assert [f.seq for f in kept] == [6, 8, 9, 10, 11] and skipped == 7
    assert shed_backlog(frames, 3)[0][:6] == [frames[i] for i in (0, 2, 4, 6, 8, 9)]  # without the bound: all kept


def test_the_back_end_counts_the_keyframes_it_skips():
    """BackendNode.shed (live: called with what waits before each feature frame) keeps what shed_backlog keeps
    and counts the keyframes among the skipped frames (stats/backend keyframes_skipped)."""
    from services.backend.node import make_node
    from services.app.system_config import load_system_config
    from shared.rig import load_rig_config

    cfg = load_system_config(None, ["loop.enabled=false", "backend.max_backlog_frames=3",
                                    "backend.max_backlog_keyframes=2"])
    node = make_node(cfg, load_rig_config(cfg.rig))
    kept, skipped = node.shed([F(0, True), F(1), F(2, True)])  # within the bounds: nothing skipped
    assert len(kept) == 3 and skipped == 0 and node.skipped_keyframes == 0
    frames = [F(i, is_keyframe=i % 2 == 0) for i in range(10)]  # keyframes 0, 2, 4, 6, 8
    kept, skipped = node.shed(frames)
    assert [f.seq for f in kept] == [6, 7, 8, 9] and skipped == 6
    assert node.skipped_keyframes == 3 and node.counters()["keyframes_skipped"]() == 3
