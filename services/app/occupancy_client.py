"""Asking the occupancy map: the same three questions of a running mapping process (over Zenoh, ``map/query``) or of
a saved map (``DIR/map/``, offline), with the encoding hidden.

::

    from services.app.occupancy_client import LiveOccupancy, SavedOccupancy

    with LiveOccupancy(TransportConfig(namespace="sigmaslam/robot0")) as occ:   # a running pipeline
        got = occ.points(np.array([[1.0, 2.0, 0.5]]))       # .state (0 unknown, 1 free, 2 occupied), .log_odds
        seg = occ.segments(start, end, radius_m=0.3)        # .hit, .hit_distance_m, .hit_point_W, .free
        box = occ.boxes(lo, hi)                             # .any_occupied, .occupied_fraction, .unknown_fraction
    occ = SavedOccupancy("runs/out")                          # the same answers from a run's saved map

Everything is in the world frame W (the causal estimate's, live; the saved map's, offline). A question the map
refuses (wrong shape, NaN, too many points) raises :class:`QueryError` with the reason; so does no answer within
``timeout_s``. How the submaps are combined: services/mapping/combined.py, docs/occupancy.md.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from services.mapping.combined import BoxAnswer, CombinedMap, PointAnswer, SegmentAnswer
from services.mapping.config import QueryConfig
from services.mapping.query_service import answer, query_message, result_of
from shared import codec, topics
from shared.messages import OccupancyAnswer, OccupancyQuery


class QueryError(ValueError):
    """The map refused a question (the reason is the message), or nobody answered it."""


class _Asking:
    """The three questions, on top of a subclass's :meth:`ask`."""

    def ask(self, q: OccupancyQuery) -> OccupancyAnswer:
        raise NotImplementedError

    def points(self, p_W: np.ndarray) -> PointAnswer:
        return result_of(self.ask(self._message("points", p_W)))

    def segments(self, start_W: np.ndarray, end_W: np.ndarray, radius_m: np.ndarray | float = 0.0) -> SegmentAnswer:
        return result_of(self.ask(self._message("segments", start_W, end_W, radius_m)))

    def boxes(self, lo_W: np.ndarray, hi_W: np.ndarray) -> BoxAnswer:
        return result_of(self.ask(self._message("boxes", lo_W, hi_W)))

    @staticmethod
    def _message(*args) -> OccupancyQuery:
        try:
            return query_message(*args)
        except ValueError as exc:
            raise QueryError(str(exc)) from None


class LiveOccupancy(_Asking):
    """Questions to the mapping process of a running pipeline, over its own Zenoh session (or ``session``)."""

    def __init__(self, cfg=None, timeout_s: float = 5.0, session=None) -> None:
        from transport.config import TransportConfig

        self.cfg = cfg or TransportConfig()
        self.timeout_s = float(timeout_s)
        self.key_expr = topics.MAP_QUERY.key_expr(self.cfg.namespace)
        self._own = session is None
        self.session = session

    def __enter__(self) -> LiveOccupancy:
        if self.session is None:
            from transport.session import open_session

            self.session = open_session(self.cfg)
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        if self._own and self.session is not None:
            self.session.close()
            self.session = None

    def ask(self, q: OccupancyQuery) -> OccupancyAnswer:
        if self.session is None:
            self.__enter__()
        for reply in self.session.get(self.key_expr, payload=codec.encode(q), timeout=self.timeout_s):
            if reply.ok is not None:
                try:
                    return codec.decode(reply.ok.payload.to_bytes(), expect=OccupancyAnswer)
                except codec.DecodeError as exc:
                    raise QueryError(f"an answer that does not decode: {exc}") from None
            raise QueryError(reply.err.payload.to_bytes().decode(errors="replace"))
        raise QueryError(f"no mapping process answered at {self.key_expr} within {self.timeout_s:g} s")


class SavedOccupancy(_Asking):
    """The same questions answered from a saved map (a run's folder or its map/ folder), without any process."""

    def __init__(self, folder: str | Path, cfg: QueryConfig | None = None) -> None:
        from services.mapping.io import load_map
        from shared.map_folder import dense_path

        path = dense_path(folder)
        if not path.is_file():
            raise FileNotFoundError(f"{folder}: no dense map ({path})")
        self.mapper = load_map(path)
        self.map = CombinedMap.of(self.mapper, cfg)

    def ask(self, q: OccupancyQuery) -> OccupancyAnswer:
        try:
            return answer(self.map, q)
        except ValueError as exc:
            raise QueryError(str(exc)) from None
