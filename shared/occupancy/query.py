"""Queries of an occupancy field at arbitrary points: voxel look-up, trilinear L and its gradient,
occupied/free/unknown state.

Voxel ``(i, j, k)`` has its centre at ``(i + 0.5, j + 0.5, k + 0.5) * voxel_size`` in the field's
frame (the submap frame M). L > 0 is occupied, L < 0 free, w == 0 unknown; the surface is L = 0.

:class:`BlockField` is a read-only view of block arrays; :meth:`BlockField.of` gives one over the
live map and :func:`near_surface_field` a compact copy holding only the refined (near-surface)
blocks, which is what the occupancy-to-point factors of the back end need (eq. 6-7).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from shared.occupancy.blocks import BlockStore, pack_keys

UNKNOWN, FREE, OCCUPIED = 0, 1, 2

# the 8 corners of a trilinear cell, in (dx, dy, dz) order with x fastest
_CORNERS = np.array([[(c >> 0) & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], np.int64)


@dataclasses.dataclass(frozen=True)
class BlockField:
    """Arrays of a block-sparse field (see :mod:`shared.occupancy.blocks` for their meaning)."""

    voxel_size: float
    block_size: int
    keys_sorted: np.ndarray  # (n,) int64
    slot_of_sorted: np.ndarray  # (n,) int64
    coarse_L: np.ndarray  # (>=n,) float32, by slot
    coarse_w: np.ndarray  # (>=n,) uint16, by slot
    vox_slot: np.ndarray  # (>=n,) int32, by slot; -1 = coarse
    Lv: np.ndarray  # (m, B, B, B) float32
    wv: np.ndarray  # (m, B, B, B) uint16

    @classmethod
    def of(cls, store: BlockStore) -> BlockField:
        n, m = store.n_blocks, store.n_refined
        return cls(store.voxel_size, store.block_size, store.keys_sorted, store.slot_of_sorted,
                   store.coarse_L[:n], store.coarse_w[:n], store.vox_slot[:n], store.Lv[:m], store.wv[:m])

    def slots(self, keys: np.ndarray) -> np.ndarray:
        n = len(self.keys_sorted)
        if n == 0:
            return np.full(np.shape(keys), -1, np.int64)
        i = np.minimum(np.searchsorted(self.keys_sorted, keys), n - 1)
        return np.where(self.keys_sorted[i] == keys, self.slot_of_sorted[i], -1)

    def voxels(self, ijk: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """L (float32) and w (uint16) of integer voxel coordinates (..., 3); unallocated: L = 0, w = 0."""
        ijk = np.asarray(ijk, np.int64)
        b = self.block_size
        slot = self.slots(pack_keys(ijk // b))
        local = ijk % b
        L = np.zeros(slot.shape, np.float32)
        w = np.zeros(slot.shape, np.uint16)
        have = slot >= 0
        s = slot[have]
        vs = self.vox_slot[s]
        fine = vs >= 0
        Lh = self.coarse_L[s].copy()
        wh = self.coarse_w[s].copy()
        lf = local[have][fine]
        Lh[fine] = self.Lv[vs[fine], lf[:, 0], lf[:, 1], lf[:, 2]]
        wh[fine] = self.wv[vs[fine], lf[:, 0], lf[:, 1], lf[:, 2]]
        L[have], w[have] = Lh, wh
        return L, w

    def nbytes(self) -> int:
        return sum(a.nbytes for a in (self.keys_sorted, self.slot_of_sorted, self.coarse_L, self.coarse_w,
                                      self.vox_slot, self.Lv, self.wv))


def near_surface_field(store: BlockStore) -> BlockField:
    """Compact copy of the refined blocks only (coarse blocks are free space far from any surface)."""
    slots = store.refined_slots()
    keys = store.keys[slots]
    order = np.argsort(keys)
    slots, keys = slots[order], keys[order]
    vs = store.vox_slot[slots]
    m = len(slots)
    return BlockField(store.voxel_size, store.block_size, keys, np.arange(m, dtype=np.int64),
                      store.coarse_L[slots].copy(), store.coarse_w[slots].copy(), np.arange(m, dtype=np.int32),
                      store.Lv[vs].copy(), store.wv[vs].copy())


def interpolate(field: BlockField, p: np.ndarray, with_gradient: bool = True
                ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """Trilinear L at points ``p`` (N, 3) [m] in the field frame, its gradient (N, 3) [1/m] and a
    validity mask (all 8 surrounding voxels observed). Invalid rows hold NaN."""
    p = np.asarray(p, np.float64).reshape(-1, 3)
    g = p / field.voxel_size - 0.5
    i0 = np.floor(g).astype(np.int64)
    f = g - i0
    L8, w8 = field.voxels(i0[:, None, :] + _CORNERS[None])  # (N, 8)
    valid = (w8 > 0).all(axis=1)
    c = L8.astype(np.float64)
    fx, fy, fz = f[:, 0:1], f[:, 1:2], f[:, 2:3]
    cx, cy, cz = _CORNERS[:, 0], _CORNERS[:, 1], _CORNERS[:, 2]
    wx = np.where(cx, fx, 1 - fx)
    wy = np.where(cy, fy, 1 - fy)
    wz = np.where(cz, fz, 1 - fz)
    L = np.sum(c * wx * wy * wz, axis=1)
    L[~valid] = np.nan
    grad = None
    if with_gradient:
        sx = np.where(cx, 1.0, -1.0)
        sy = np.where(cy, 1.0, -1.0)
        sz = np.where(cz, 1.0, -1.0)
        grad = np.stack([np.sum(c * sx * wy * wz, axis=1), np.sum(c * wx * sy * wz, axis=1),
                         np.sum(c * wx * wy * sz, axis=1)], axis=1) / field.voxel_size
        grad[~valid] = np.nan
    return L, grad, valid


def state(field: BlockField, p: np.ndarray, occupied_above: float = 0.0) -> np.ndarray:
    """UNKNOWN / FREE / OCCUPIED (int8) of the voxel holding each point (N, 3) [m]."""
    ijk = np.floor(np.asarray(p, np.float64).reshape(-1, 3) / field.voxel_size).astype(np.int64)
    L, w = field.voxels(ijk)
    out = np.where(L > occupied_above, OCCUPIED, FREE).astype(np.int8)
    out[w == 0] = UNKNOWN
    return out
