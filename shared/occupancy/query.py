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

import numba as nb
import numpy as np

from shared.occupancy.blocks import _BITS, _OFF, BlockStore

UNKNOWN, FREE, OCCUPIED = 0, 1, 2


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
        flat = np.ascontiguousarray(ijk.reshape(-1, 3))
        L = np.empty(len(flat), np.float32)
        w = np.empty(len(flat), np.uint16)
        _voxels(flat, self.block_size, self.keys_sorted, self.slot_of_sorted, self.coarse_L, self.coarse_w,
                self.vox_slot, self.Lv, self.wv, L, w)
        return L.reshape(ijk.shape[:-1]), w.reshape(ijk.shape[:-1])

    def nbytes(self) -> int:
        return sum(a.nbytes for a in (self.keys_sorted, self.slot_of_sorted, self.coarse_L, self.coarse_w,
                                      self.vox_slot, self.Lv, self.wv))


@nb.njit(cache=True, inline="always")
def _voxel(i, j, k, b, keys_sorted, slot_of_sorted, coarse_L, coarse_w, vox_slot, Lv, wv, memo):
    """L and w of voxel (i, j, k): its block's key (blocks.pack_keys' packing), a binary search in the sorted keys
    (skipped when the block is the one of the previous call, kept in ``memo`` = [key, slot]: the 8 corners of a
    trilinear cell mostly share one), then the block's coarse value or its voxel; unallocated: 0, 0. A slot or voxel
    row beyond the arrays (read from a map that grows in another thread) reads as unallocated, never out of bounds."""
    key = np.int64(0)
    for c in (i // b + _OFF, j // b + _OFF, k // b + _OFF):  # floor division, as Python's
        if c < 0 or c >= 2 * _OFF:  # beyond the packable range: never allocated
            return np.float32(0.0), np.uint16(0)
        key = (key << _BITS) | c
    if key != memo[0]:
        n = len(keys_sorted)
        lo, hi = 0, n
        while lo < hi:
            mid = (lo + hi) >> 1
            if keys_sorted[mid] < key:
                lo = mid + 1
            else:
                hi = mid
        memo[0], memo[1] = key, (slot_of_sorted[lo] if lo < n and lo < len(slot_of_sorted) and keys_sorted[lo] == key
                                 else -1)
    slot = memo[1]
    if slot < 0 or slot >= len(coarse_L) or slot >= len(coarse_w) or slot >= len(vox_slot):  # arrays read while
        # the map grew in another thread (a live snapshot) may differ in length
        return np.float32(0.0), np.uint16(0)
    v = vox_slot[slot]
    if v < 0:
        return coarse_L[slot], coarse_w[slot]
    if v >= Lv.shape[0]:  # refined after the snapshot was taken: not in its voxel pool
        return np.float32(0.0), np.uint16(0)
    return Lv[v, i % b, j % b, k % b], wv[v, i % b, j % b, k % b]


@nb.njit(cache=True)
def _voxels(ijk, b, keys_sorted, slot_of_sorted, coarse_L, coarse_w, vox_slot, Lv, wv, L, w):
    memo = np.full(2, -1, np.int64)
    for r in range(ijk.shape[0]):
        L[r], w[r] = _voxel(ijk[r, 0], ijk[r, 1], ijk[r, 2], b, keys_sorted, slot_of_sorted, coarse_L, coarse_w,
                            vox_slot, Lv, wv, memo)


@nb.njit(cache=True)
def _trilinear(p, vs, b, keys_sorted, slot_of_sorted, coarse_L, coarse_w, vox_slot, Lv, wv, L, grad, valid):
    """interpolate(), compiled: per point the 8 voxel centres around it, their weights and, when ``grad`` has a row
    per point, L's gradient."""
    with_grad = grad.shape[0] == p.shape[0]
    memo = np.full(2, -1, np.int64)
    c = np.empty(8)
    for r in range(p.shape[0]):
        g0, g1, g2 = p[r, 0] / vs - 0.5, p[r, 1] / vs - 0.5, p[r, 2] / vs - 0.5
        i0, j0, k0 = np.floor(g0), np.floor(g1), np.floor(g2)
        fx, fy, fz = g0 - i0, g1 - j0, g2 - k0
        ok = True
        for q in range(8):  # corner q = (dx, dy, dz), x fastest (the order of o2p_factor._CORNERS)
            Lq, wq = _voxel(np.int64(i0) + (q & 1), np.int64(j0) + ((q >> 1) & 1), np.int64(k0) + ((q >> 2) & 1),
                            b, keys_sorted, slot_of_sorted, coarse_L, coarse_w, vox_slot, Lv, wv, memo)
            c[q] = Lq
            ok = ok and wq > 0
        valid[r] = ok
        if not ok:
            L[r] = np.nan
            if with_grad:
                grad[r, 0] = grad[r, 1] = grad[r, 2] = np.nan
            continue
        # along x, then y, then z (the trilinear form and its partial derivatives)
        c00, c10 = c[0] * (1 - fx) + c[1] * fx, c[2] * (1 - fx) + c[3] * fx
        c01, c11 = c[4] * (1 - fx) + c[5] * fx, c[6] * (1 - fx) + c[7] * fx
        d00, d10, d01, d11 = c[1] - c[0], c[3] - c[2], c[5] - c[4], c[7] - c[6]
        c0, c1 = c00 * (1 - fy) + c10 * fy, c01 * (1 - fy) + c11 * fy
        L[r] = c0 * (1 - fz) + c1 * fz
        if not with_grad:
            continue
        grad[r, 0] = ((d00 * (1 - fy) + d10 * fy) * (1 - fz) + (d01 * (1 - fy) + d11 * fy) * fz) / vs
        grad[r, 1] = ((c10 - c00) * (1 - fz) + (c11 - c01) * fz) / vs
        grad[r, 2] = (c1 - c0) / vs


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
    p = np.ascontiguousarray(np.asarray(p, np.float64).reshape(-1, 3))
    n = len(p)
    L, grad, valid = np.empty(n), np.empty((n if with_gradient else 0, 3)), np.empty(n, np.bool_)
    _trilinear(p, float(field.voxel_size), field.block_size, field.keys_sorted, field.slot_of_sorted, field.coarse_L,
               field.coarse_w, field.vox_slot, field.Lv, field.wv, L, grad, valid)
    return L, (grad if with_gradient else None), valid


def state(field: BlockField, p: np.ndarray, occupied_above: float = 0.0) -> np.ndarray:
    """UNKNOWN / FREE / OCCUPIED (int8) of the voxel holding each point (N, 3) [m]."""
    ijk = np.floor(np.asarray(p, np.float64).reshape(-1, 3) / field.voxel_size).astype(np.int64)
    L, w = field.voxels(ijk)
    out = np.where(L > occupied_above, OCCUPIED, FREE).astype(np.int8)
    out[w == 0] = UNKNOWN
    return out


def warm_up() -> None:
    """Load the compiled kernels (numba's on-disk cache; compile on a first run) with an empty field, so that a
    process's first real query does not pay for it: ~0.1-0.3 s, which the back end's first occupancy-to-point
    terms used to spend while it initialised."""
    field = BlockField.of(BlockStore(0.1))
    interpolate(field, np.zeros((1, 3)))
    field.voxels(np.zeros((1, 3), np.int64))
