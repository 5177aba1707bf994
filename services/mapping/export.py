"""The compact near-surface field of a submap as an :class:`~shared.messages.OccupancyField` message and
back into a :class:`~services.mapping.query.BlockField` that the query functions accept."""

from __future__ import annotations

import numpy as np

from services.mapping.blocks import pack_keys, unpack_keys
from services.mapping.query import BlockField, near_surface_field
from services.mapping.submaps import Submap
from shared.codec import Header
from shared.messages import OccupancyField


def field_message(submap: Submap, l_min: float, stamp_ns: int | None = None, seq: int = 0) -> OccupancyField:
    """The refined (near-surface) blocks of ``submap`` with its current pose."""
    f = near_surface_field(submap.store)
    return OccupancyField(header=Header(stamp_ns=submap.anchor_stamp_ns if stamp_ns is None else stamp_ns, seq=seq,
                                        frame_id=f"M{submap.id}"),
                          submap_id=submap.id, T_WM=submap.T_WM, voxel_size_m=f.voxel_size, l_min=float(l_min),
                          block_ijk=unpack_keys(f.keys_sorted).astype(np.int32), log_odds=f.Lv, counts=f.wv)


def field_of_message(msg: OccupancyField) -> BlockField:
    """Query-ready field of a received message (arrays are used as they are, read-only)."""
    keys = pack_keys(np.asarray(msg.block_ijk, np.int64))
    order = np.argsort(keys, kind="stable")
    n = len(keys)
    B = msg.log_odds.shape[1] if n else 8
    return BlockField(float(msg.voxel_size_m), int(B), keys[order], order.astype(np.int64), np.zeros(n, np.float32),
                      np.zeros(n, np.uint16), np.arange(n, dtype=np.int32), np.asarray(msg.log_odds), np.asarray(msg.counts))
