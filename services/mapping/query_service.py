"""``map/query`` requests answered by a :class:`~services.mapping.combined.CombinedMap`, and answers turned back
into the query results: the one encoding of the question, used by the mapping process (live), by the client
(services/app/occupancy_client.py) and by ``sigmaslam map query`` on a saved map."""

from __future__ import annotations

import numpy as np

from services.mapping.combined import BoxAnswer, CombinedMap, PointAnswer, SegmentAnswer
from shared.codec import Header
from shared.messages import OccupancyAnswer, OccupancyQuery

KINDS = ("points", "segments", "boxes")


def query_message(kind: str, a_W: np.ndarray, b_W: np.ndarray | None = None, radius_m: np.ndarray | float = 0.0,
                  stamp_ns: int = 0) -> OccupancyQuery:
    """The request of one query; ValueError for a kind that is not one of :data:`KINDS` or arrays that are not
    (N, 3) (the server checks the values)."""
    if kind not in KINDS:
        raise ValueError(f"query kind {kind!r} is not one of {KINDS}")
    a = _rows(a_W, "a_W")
    b = np.zeros((0, 3)) if b_W is None else _rows(b_W, "b_W")
    r = np.atleast_1d(np.asarray(radius_m, np.float64)) if kind == "segments" else np.zeros(0)
    return OccupancyQuery(header=Header(stamp_ns=int(stamp_ns), frame_id="W"), kind=kind, a_W=a, b_W=b, radius_m=r)


def _rows(p, name: str) -> np.ndarray:
    try:
        p = np.ascontiguousarray(p, np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}: not numbers ({exc})") from None
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"{name} must be an (N, 3) array, got shape {p.shape}")
    return p


def answer(cm: CombinedMap, q: OccupancyQuery, stamp_ns: int = 0) -> OccupancyAnswer:
    """The combined map's answer to ``q``; ValueError (with the reason) for a request it refuses."""
    if q.header.frame_id not in ("W", ""):
        raise ValueError(f"queries are answered in W, not in {q.header.frame_id!r}")
    empty = {"state": np.zeros(0, np.int8), "log_odds": np.zeros(0, np.float32), "submaps": np.zeros(0, np.int16),
             "hit": np.zeros(0, bool), "hit_distance_m": np.zeros(0), "hit_point_W": np.zeros((0, 3)),
             "free": np.zeros(0, bool), "any_occupied": np.zeros(0, bool), "occupied_fraction": np.zeros(0),
             "unknown_fraction": np.zeros(0)}
    if q.kind == "points":
        if len(q.b_W) or len(q.radius_m):
            raise ValueError("a points query has only a_W")
        p = cm.points(q.a_W)
        got = {"state": p.state, "log_odds": p.log_odds, "submaps": p.submaps}
    elif q.kind == "segments":
        if len(q.radius_m) not in (1, len(q.a_W)):
            raise ValueError(f"segments need one radius or one per segment, got {len(q.radius_m)} for {len(q.a_W)}")
        s = cm.segments(q.a_W, q.b_W, q.radius_m if len(q.radius_m) == len(q.a_W) else q.radius_m[0])
        got = {"hit": s.hit, "hit_distance_m": s.hit_distance_m, "hit_point_W": s.hit_point_W, "free": s.free,
               "unknown_fraction": s.unknown_fraction}
    elif q.kind == "boxes":
        b = cm.boxes(q.a_W, q.b_W)
        got = {"any_occupied": b.any_occupied, "occupied_fraction": b.occupied_fraction,
               "unknown_fraction": b.unknown_fraction}
    else:
        raise ValueError(f"query kind {q.kind!r} is not one of {KINDS}")
    return OccupancyAnswer(header=Header(stamp_ns=int(stamp_ns), seq=q.header.seq, frame_id="W"), kind=q.kind,
                           **{**empty, **got})


def result_of(msg: OccupancyAnswer) -> PointAnswer | SegmentAnswer | BoxAnswer:
    """The query result an answer message carries (arrays copied out of the received buffer)."""
    c = {k: np.array(getattr(msg, k)) for k in ("state", "log_odds", "submaps", "hit", "hit_distance_m", "hit_point_W",
                                                "free", "any_occupied", "occupied_fraction", "unknown_fraction")}
    if msg.kind == "points":
        return PointAnswer(c["state"], c["log_odds"], c["submaps"])
    if msg.kind == "segments":
        return SegmentAnswer(c["hit"], c["hit_distance_m"], c["hit_point_W"], c["free"], c["unknown_fraction"])
    if msg.kind == "boxes":
        return BoxAnswer(c["any_occupied"], c["occupied_fraction"], c["unknown_fraction"])
    raise ValueError(f"an answer of unknown kind {msg.kind!r}")
