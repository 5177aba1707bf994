"""A received :class:`~shared.messages.OccupancyField` message as a :class:`~shared.occupancy.query.BlockField`
that the query functions accept (the mapping's side, submap -> message, is :mod:`services.mapping.export`)."""

from __future__ import annotations

import numpy as np

from shared.messages import OccupancyField
from shared.occupancy.blocks import pack_keys
from shared.occupancy.query import BlockField


def field_of_message(msg: OccupancyField) -> BlockField:
    """Query-ready field of a received message (arrays are used as they are, read-only)."""
    keys = pack_keys(np.asarray(msg.block_ijk, np.int64))
    order = np.argsort(keys, kind="stable")
    n = len(keys)
    B = msg.log_odds.shape[1] if n else 8
    return BlockField(float(msg.voxel_size_m), int(B), keys[order], order.astype(np.int64), np.zeros(n, np.float32),
                      np.zeros(n, np.uint16), np.arange(n, dtype=np.int32), np.asarray(msg.log_odds), np.asarray(msg.counts))
