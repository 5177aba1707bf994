"""Sparse voxel-block storage of one occupancy field: mean log-odds L and observation count w.

Space is cut into cubic blocks of ``B^3`` voxels (B = 8 by default). A block is addressed by its
integer block coordinates, packed into one int64 key. Each allocated block has a *slot*; a block is
either *coarse* (one L and w for all its voxels: free space carved as a whole) or *refined* (its
own ``B^3`` voxels in the voxel pool, allocated when a surface comes near). A voxel with w == 0 is
unknown.

The arrays are what :class:`BlockField` (see :mod:`shared.occupancy.query`) reads, so the same
query code serves the live map and a compact exported copy of its near-surface blocks.
"""

from __future__ import annotations

import numpy as np

_BITS = 21
_OFF = 1 << (_BITS - 1)
_MASK = (1 << _BITS) - 1


def pack_keys(ijk: np.ndarray) -> np.ndarray:
    """int64 keys of integer block coordinates (..., 3), each within [-2^20, 2^20)."""
    ijk = np.asarray(ijk, dtype=np.int64)
    if ijk.size and (ijk.min() < -_OFF or ijk.max() >= _OFF):
        raise ValueError("block coordinates out of the packable range [-2^20, 2^20)")
    s = ijk + _OFF
    return (s[..., 0] << (2 * _BITS)) | (s[..., 1] << _BITS) | s[..., 2]


def unpack_keys(keys: np.ndarray) -> np.ndarray:
    """Block coordinates (..., 3) int64 of packed keys."""
    keys = np.asarray(keys, dtype=np.int64)
    return np.stack([((keys >> (2 * _BITS)) & _MASK) - _OFF, ((keys >> _BITS) & _MASK) - _OFF,
                     (keys & _MASK) - _OFF], axis=-1)


class BlockStore:
    """Growable block arrays with a sorted key index (vectorised look-up and insertion)."""

    def __init__(self, voxel_size: float, block_size: int = 8) -> None:
        self.voxel_size = float(voxel_size)
        self.block_size = int(block_size)
        b = self.block_size
        self.keys_sorted = np.empty(0, np.int64)  # sorted keys of all allocated blocks
        self.slot_of_sorted = np.empty(0, np.int64)  # slot of each sorted key
        self.n_blocks = 0
        self.n_refined = 0  # voxel-pool rows handed out (including freed ones in free_rows)
        self.free_rows = np.empty(0, np.int32)  # voxel-pool rows given back by unrefine()
        cap = 64
        self.keys = np.empty(cap, np.int64)  # key of each slot
        self.coarse_L = np.zeros(cap, np.float32)
        self.coarse_w = np.zeros(cap, np.uint16)
        self.vox_slot = np.full(cap, -1, np.int32)  # row in the voxel pool, -1 = coarse
        self.Lv = np.zeros((cap, b, b, b), np.float32)
        self.wv = np.zeros((cap, b, b, b), np.uint16)

    # ------------------------------------------------------------------ index

    @property
    def block_m(self) -> float:
        return self.voxel_size * self.block_size

    def lookup(self, keys: np.ndarray) -> np.ndarray:
        """Slots of ``keys`` (-1 where not allocated)."""
        keys = np.asarray(keys, np.int64)
        if self.n_blocks == 0:
            return np.full(keys.shape, -1, np.int64)
        i = np.searchsorted(self.keys_sorted, keys)
        i = np.minimum(i, self.n_blocks - 1)
        found = self.keys_sorted[i] == keys
        return np.where(found, self.slot_of_sorted[i], -1)

    def insert(self, keys: np.ndarray) -> np.ndarray:
        """Slots of unique ``keys``, allocating missing blocks as coarse and unknown."""
        keys = np.asarray(keys, np.int64)
        slots = self.lookup(keys)
        new = slots < 0
        if new.any():
            new_keys = np.unique(keys[new])
            n0 = self.n_blocks
            n1 = n0 + len(new_keys)
            self._grow_blocks(n1)
            self.keys[n0:n1] = new_keys
            self.coarse_L[n0:n1] = 0.0
            self.coarse_w[n0:n1] = 0
            self.vox_slot[n0:n1] = -1
            all_keys = np.concatenate([self.keys_sorted, new_keys])
            all_slots = np.concatenate([self.slot_of_sorted, np.arange(n0, n1, dtype=np.int64)])
            order = np.argsort(all_keys, kind="stable")
            self.keys_sorted, self.slot_of_sorted = all_keys[order], all_slots[order]
            self.n_blocks = n1
            slots = self.lookup(keys)
        return slots

    def refine(self, slots: np.ndarray) -> None:
        """Give coarse blocks among ``slots`` their own voxels, initialised with the coarse value."""
        slots = np.unique(np.asarray(slots, np.int64))
        slots = slots[self.vox_slot[slots] < 0]
        if len(slots) == 0:
            return
        reuse = self.free_rows[: len(slots)]
        self.free_rows = self.free_rows[len(reuse):]
        v0 = self.n_refined
        v1 = v0 + len(slots) - len(reuse)
        self._grow_voxels(v1)
        rows = np.concatenate([reuse, np.arange(v0, v1, dtype=np.int32)])
        self.vox_slot[slots] = rows
        self.Lv[rows] = self.coarse_L[slots][:, None, None, None]
        self.wv[rows] = self.coarse_w[slots][:, None, None, None]
        self.n_refined = v1

    def unrefine(self, slots: np.ndarray) -> None:
        """Turn refined blocks back into coarse ones (only for blocks whose voxels are all unknown)."""
        slots = np.asarray(slots, np.int64)
        rows = self.vox_slot[slots]
        slots, rows = slots[rows >= 0], rows[rows >= 0]
        if len(slots) == 0:
            return
        self.vox_slot[slots] = -1
        self.coarse_L[slots] = 0.0
        self.coarse_w[slots] = 0
        self.free_rows = np.concatenate([self.free_rows, rows.astype(np.int32)])

    def coarsen_free(self, below: float) -> int:
        """Turn refined blocks whose voxels are all observed and all below ``below`` (clearly free: no
        surface within a voxel of them) into coarse ones (mean L, least w); returns how many."""
        slots = self.refined_slots()
        if len(slots) == 0:
            return 0
        rows = self.vox_slot[slots]
        Lv, wv = self.Lv[rows], self.wv[rows]
        free = (wv > 0).all(axis=(1, 2, 3)) & (Lv < below).all(axis=(1, 2, 3))
        slots, Lv, wv = slots[free], Lv[free], wv[free]
        self.unrefine(slots)
        self.coarse_L[slots] = Lv.mean(axis=(1, 2, 3))
        self.coarse_w[slots] = wv.min(axis=(1, 2, 3))
        return int(len(slots))

    def _grow_blocks(self, n: int) -> None:
        cap = len(self.keys)
        if n <= cap:
            return
        cap = max(n, 2 * cap)
        self.keys = _resized(self.keys, cap, 0)
        self.coarse_L = _resized(self.coarse_L, cap, 0)
        self.coarse_w = _resized(self.coarse_w, cap, 0)
        self.vox_slot = _resized(self.vox_slot, cap, -1)

    def _grow_voxels(self, n: int) -> None:
        cap = len(self.Lv)
        if n <= cap:
            return
        cap = max(n, 2 * cap)
        self.Lv = _resized(self.Lv, cap, 0)
        self.wv = _resized(self.wv, cap, 0)

    # ------------------------------------------------------------------ views

    def block_coords(self, slots: np.ndarray) -> np.ndarray:
        return unpack_keys(self.keys[np.asarray(slots, np.int64)])

    def refined_slots(self) -> np.ndarray:
        return np.flatnonzero(self.vox_slot[: self.n_blocks] >= 0)

    def nbytes(self) -> int:
        """Bytes of the used part of the storage (index, coarse values, voxel pool)."""
        b3 = self.block_size ** 3
        per_block = 8 + 8 + 8 + 4 + 2 + 4  # sorted key + slot + key + coarse L + coarse w + vox slot
        return self.n_blocks * per_block + (self.n_refined - len(self.free_rows)) * b3 * (4 + 2)

    def arrays(self) -> dict[str, np.ndarray]:
        """The used storage as plain arrays (for saving); :meth:`from_arrays` inverts it."""
        n = self.n_blocks
        vox_slot = self.vox_slot[:n].copy()
        refined = np.flatnonzero(vox_slot >= 0)
        rows = vox_slot[refined]
        vox_slot[refined] = np.arange(len(refined), dtype=np.int32)  # compact: drop freed rows
        return {"keys": self.keys[:n].copy(), "coarse_L": self.coarse_L[:n].copy(), "coarse_w": self.coarse_w[:n].copy(),
                "vox_slot": vox_slot, "Lv": self.Lv[rows], "wv": self.wv[rows],
                "voxel_size": np.float64(self.voxel_size), "block_size": np.int64(self.block_size)}

    @classmethod
    def from_arrays(cls, a: dict[str, np.ndarray]) -> BlockStore:
        store = cls(float(a["voxel_size"]), int(a["block_size"]))
        b = store.block_size
        n, m = len(a["keys"]), len(a["Lv"])
        if a["Lv"].shape[1:] != (b, b, b) or len(a["coarse_L"]) != n or len(a["vox_slot"]) != n:
            raise ValueError("inconsistent block arrays")
        store.keys, store.coarse_L = a["keys"].astype(np.int64), a["coarse_L"].astype(np.float32)
        store.coarse_w, store.vox_slot = a["coarse_w"].astype(np.uint16), a["vox_slot"].astype(np.int32)
        store.Lv, store.wv = a["Lv"].astype(np.float32), a["wv"].astype(np.uint16)
        store.n_blocks, store.n_refined = n, m
        if n == 0:  # keep growable arrays non-empty
            store._grow_blocks(1)
        if m == 0:
            store._grow_voxels(1)
        order = np.argsort(store.keys[:n], kind="stable")
        store.keys_sorted, store.slot_of_sorted = store.keys[:n][order], order.astype(np.int64)
        return store


def _resized(a: np.ndarray, n: int, fill: float) -> np.ndarray:
    out = np.full((n,) + a.shape[1:], fill, a.dtype)
    out[: len(a)] = a[: min(len(a), n)]
    return out
