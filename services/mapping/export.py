"""The compact near-surface field of a submap as an :class:`~shared.messages.OccupancyField` message (back into
a query-ready field on the receiving side: :func:`shared.occupancy.message.field_of_message`)."""

from __future__ import annotations

import numpy as np

from shared.occupancy.blocks import unpack_keys
from shared.occupancy.query import near_surface_field
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

