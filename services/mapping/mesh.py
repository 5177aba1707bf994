"""Marching cubes of a block store at the L = 0 iso-surface, chunk by chunk, re-meshing only chunks
whose blocks changed.

A chunk is ``C^3`` blocks; its dense volume takes one extra voxel layer from the next blocks in +x,
+y, +z so that neighbouring chunks' meshes meet. Cells with an unknown corner (w == 0) produce no
triangles: the surface ends where observations end instead of closing on unknown space.
"""

from __future__ import annotations

import numpy as np
from skimage.measure import marching_cubes

from shared.occupancy.blocks import BlockStore, pack_keys, unpack_keys
from shared.occupancy.query import BlockField

_OFFSETS = np.array([[a, b, c] for a in (0, 1) for b in (0, 1) for c in (0, 1)], np.int64)


def dense_volume(field: BlockField, block_lo: np.ndarray, n_blocks: int, n_vox: int) -> tuple[np.ndarray, np.ndarray, bool]:
    """L (float32) and w (uint16) on the voxels ``block_lo * B + [0, n_vox)`` per axis, gathered from the
    ``n_blocks^3`` blocks starting at ``block_lo``; also whether any of them is refined."""
    B = field.block_size
    grid = np.stack(np.meshgrid(*[np.arange(n_blocks)] * 3, indexing="ij"), axis=-1).reshape(-1, 3) + block_lo
    slots = field.slots(pack_keys(grid))
    L = np.zeros((len(grid), B, B, B), np.float32)
    w = np.zeros((len(grid), B, B, B), np.uint16)
    have = slots >= 0
    rows = np.full(len(grid), -1, np.int64)
    rows[have] = field.vox_slot[slots[have]]
    coarse = have & (rows < 0)
    L[coarse] = field.coarse_L[slots[coarse]][:, None, None, None]
    w[coarse] = field.coarse_w[slots[coarse]][:, None, None, None]
    fine = rows >= 0
    L[fine] = field.Lv[rows[fine]]
    w[fine] = field.wv[rows[fine]]
    n = n_blocks
    L = L.reshape(n, n, n, B, B, B).transpose(0, 3, 1, 4, 2, 5).reshape(n * B, n * B, n * B)
    w = w.reshape(n, n, n, B, B, B).transpose(0, 3, 1, 4, 2, 5).reshape(n * B, n * B, n * B)
    return L[:n_vox, :n_vox, :n_vox], w[:n_vox, :n_vox, :n_vox], bool(fine.any())


def mesh_volume(L: np.ndarray, w: np.ndarray, origin_voxel: np.ndarray, voxel_size: float) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) float32 [m] and faces (F, 3) int32 of the L = 0 surface of a dense volume whose
    [0, 0, 0] voxel is ``origin_voxel``; only cells with all 8 corners observed."""
    known = w > 0
    empty = (np.empty((0, 3), np.float32), np.empty((0, 3), np.int32))
    if not (known & (L > 0)).any() or not (known & (L < 0)).any():
        return empty
    cell_ok = np.ones(tuple(s - 1 for s in L.shape), bool)
    for o in _OFFSETS:
        cell_ok &= known[o[0]:o[0] + L.shape[0] - 1, o[1]:o[1] + L.shape[1] - 1, o[2]:o[2] + L.shape[2] - 1]
    if not cell_ok.any():
        return empty
    vol = np.where(known, L, np.float32(1.0))
    verts, faces, _, _ = marching_cubes(vol, level=0.0, gradient_direction="descent", allow_degenerate=False)
    if len(faces) == 0:
        return empty
    cell = np.floor(verts[faces].mean(axis=1)).astype(np.int64)
    cell = np.minimum(cell, np.array(cell_ok.shape) - 1)
    faces = faces[cell_ok[cell[:, 0], cell[:, 1], cell[:, 2]]]
    if len(faces) == 0:
        return empty
    used, inverse = np.unique(faces, return_inverse=True)
    verts_m = ((verts[used] + origin_voxel + 0.5) * voxel_size).astype(np.float32)
    return verts_m, inverse.reshape(-1, 3).astype(np.int32)


class ChunkMesher:
    """Cached per-chunk meshes of one block store; :meth:`mark` changed blocks, :meth:`update` re-meshes."""

    def __init__(self, chunk_blocks: int = 4) -> None:
        self.chunk_blocks = int(chunk_blocks)
        self.meshes: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.pending = np.empty(0, np.int64)  # chunk keys waiting to be re-meshed
        self.version = 0  # incremented whenever a chunk mesh changed

    def mark(self, store: BlockStore, slots: np.ndarray) -> None:
        """Queue the chunks touched by changed blocks (and the lower neighbours whose padding they are)."""
        if len(slots) == 0:
            return
        C = self.chunk_blocks
        b = store.block_coords(slots)
        chunk = b // C
        at_lo = (b % C) == 0
        cands = [chunk - o for o in _OFFSETS if not o.any()] + \
                [(chunk - o)[np.all(at_lo | (o == 0), axis=1)] for o in _OFFSETS if o.any()]
        keys = pack_keys(np.concatenate(cands))
        self.pending = np.unique(np.concatenate([self.pending, keys]))

    def update(self, store: BlockStore, budget_s: float | None = None) -> int:
        """Re-mesh pending chunks (all, or until ``budget_s`` of work); returns how many were re-meshed."""
        import time

        t0 = time.perf_counter()
        field = BlockField.of(store)
        C, B = self.chunk_blocks, store.block_size
        done = 0
        for key in self.pending:
            c = unpack_keys(key)
            L, w, any_fine = dense_volume(field, c * C, C + 1, C * B + 1)
            mesh = mesh_volume(L, w, c * C * B, store.voxel_size) if any_fine else None
            if mesh is not None and len(mesh[1]):
                self.meshes[int(key)] = mesh
            else:
                self.meshes.pop(int(key), None)
            done += 1
            self.version += 1
            if budget_s is not None and time.perf_counter() - t0 > budget_s:
                break
        self.pending = self.pending[done:]
        return done

    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """The whole mesh (vertices in the store's frame [m], faces) from the cached chunks."""
        if not self.meshes:
            return np.empty((0, 3), np.float32), np.empty((0, 3), np.int32)
        parts = [self.meshes[k] for k in sorted(self.meshes)]
        offs = np.cumsum([0] + [len(v) for v, _ in parts[:-1]])
        verts = np.concatenate([v for v, _ in parts])
        faces = np.concatenate([f + o for (_, f), o in zip(parts, offs)]).astype(np.int32)
        return verts, faces
