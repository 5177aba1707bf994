"""Affine refinement of tracks against the patch where each feature was first seen (``frontend.klt_affine``).

Frame-to-frame KLT matches a square window by translation only. As the camera moves, a feature's patch grows,
shrinks, turns and shears, and the translation that best fits the changed patch is not where the point went: on
V1_02's replica the tracks drift from the true point by ~0.15 px after 1-2 frames to ~1 px after 20-40, growing
with the scale change and roll since the feature was first seen (tools/eval/track_error.py). Here each track keeps
its first patch (the template) and an affine warp x -> t + A x of it into the current image, with a gain and an
offset for the brightness; the warp is refined by inverse-compositional Gauss-Newton (Baker & Matthews 2004),
started at the frame-to-frame KLT position and the last A. The template does not drift, so the track does not
either.

All tracks of a camera are solved together: one ``cv2.remap`` samples every warped patch, and the 6x6 systems are
batched. The templates live in a store that only grows between compactions; the tracker drops and adds tracks every
frame but refines at keyframes only, so per frame the store moves row numbers, not patches (stop 54).
"""

from __future__ import annotations

import functools

import cv2
import numpy as np

# per track: mean-free template values (S*S), template gradient x and y (2, S*S), inverse Gauss-Newton Hessian (6, 6),
# warp A (2, 2); float32, plus the values' norm
_FIELDS = ("values", "norms", "grad", "h_inv", "A")


class AffineTemplates:
    """The templates of N tracks, in track order. ``side`` S is odd; template pixel (i, j) sits at (j - c, i - c)
    from the feature, c = (S - 1) / 2. :meth:`keep`, :meth:`append` and :meth:`replace` follow the tracker's
    tracks; the fields (``values``, ``norms``, ``grad``, ``h_inv``, ``A``) are read as arrays in track order
    (copies), and A is written through :meth:`set_A`."""

    def __init__(self, side: int, values, norms, grad, h_inv, A) -> None:
        self.side = int(side)
        self._store = {"values": values, "norms": norms, "grad": grad, "h_inv": h_inv, "A": A}
        self._size = len(values)  # rows of the store in use (some may belong to dropped tracks)
        self._rows = np.arange(self._size)  # track -> row of the store

    @classmethod
    def empty(cls, side: int) -> "AffineTemplates":
        s2 = side * side
        z = np.zeros
        return cls(side, z((0, s2), np.float32), z(0, np.float32), z((0, 2, s2), np.float32),
                   z((0, 6, 6), np.float32), z((0, 2, 2), np.float32))

    def __len__(self) -> int:
        return len(self._rows)

    def __getattr__(self, name: str) -> np.ndarray:
        if name in _FIELDS:
            return self._store[name][self._rows]
        raise AttributeError(name)

    def set_A(self, mask: np.ndarray, A: np.ndarray) -> None:
        """The warps of the tracks in ``mask`` (N,) become ``A`` (mask.sum(), 2, 2)."""
        self._store["A"][self._rows[mask]] = A

    def keep(self, mask: np.ndarray) -> None:
        self._rows = self._rows[mask]

    def append(self, other: "AffineTemplates") -> None:
        n = len(other)
        if not n:
            return
        if self._size + n > len(self._store["values"]):
            self._compact(len(self._rows) + n)
        for f in _FIELDS:
            self._store[f][self._size:self._size + n] = getattr(other, f)
        self._rows = np.concatenate([self._rows, np.arange(self._size, self._size + n)])
        self._size += n

    def replace(self, idx: np.ndarray, other: "AffineTemplates") -> None:
        """Tracks ``idx`` start over from ``other``'s templates (same order)."""
        for f in _FIELDS:
            self._store[f][self._rows[idx]] = getattr(other, f)

    def _compact(self, need: int) -> None:
        """Keep only the rows of live tracks, with room for ``need`` tracks and as many again."""
        cap = max(2 * need, 64)
        for f, a in self._store.items():
            new = np.zeros((cap, *a.shape[1:]), a.dtype)
            new[:len(self._rows)] = a[self._rows]
            self._store[f] = new
        self._size = len(self._rows)
        self._rows = np.arange(self._size)


@functools.lru_cache(maxsize=8)
def _grid(side: int) -> np.ndarray:
    """(2, S*S) float32 template pixel offsets from the feature (x, y); built once per side, read-only."""
    c = (side - 1) / 2.0
    y, x = np.mgrid[0:side, 0:side].astype(np.float32) - c
    grid = np.stack([x.ravel(), y.ravel()])
    grid.flags.writeable = False
    return grid


def _sample(image: np.ndarray, t: np.ndarray, A: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """(N, K) float32: ``image`` at t + A x for every template offset x of ``grid`` (2, K), bilinear."""
    pts = t[:, :, None] + A @ grid  # (N, 2, K)
    return cv2.remap(image, pts[:, 0], pts[:, 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
                     ).astype(np.float32)


def _steepest_descent(grad: np.ndarray, side: int) -> np.ndarray:
    """(N, K, 6): d(template at t + A x)/dp for p = (a11, a12, a21, a22, tx, ty) at A = I, from the template's
    gradient (N, 2, K): rows (x, y, 0, 0, 1, 0) and (0, 0, x, y, 0, 1) weighted by gx and gy."""
    x, y = _grid(side)
    gx, gy = grad[:, 0], grad[:, 1]
    return np.stack([gx * x, gx * y, gy * x, gy * y, gx, gy], axis=2)


def make_templates(image: np.ndarray, uv: np.ndarray, side: int) -> AffineTemplates:
    """Templates of the features at ``uv`` (N,2) in ``image`` (uint8): the patch, its gradient (central differences
    on a patch one pixel wider) and the inverse Gauss-Newton Hessian of the affine warp; A = identity."""
    uv = np.asarray(uv, np.float32).reshape(-1, 2)
    n = len(uv)
    if n == 0:
        return AffineTemplates.empty(side)
    eye = np.tile(np.eye(2, dtype=np.float32), (n, 1, 1))
    wide = _sample(image, uv, eye, _grid(side + 2)).reshape(n, side + 2, side + 2)
    t = wide[:, 1:-1, 1:-1].reshape(n, -1)
    grad = np.stack([0.5 * (wide[:, 1:-1, 2:] - wide[:, 1:-1, :-2]).reshape(n, -1),
                     0.5 * (wide[:, 2:, 1:-1] - wide[:, :-2, 1:-1]).reshape(n, -1)], axis=1)
    sd = _steepest_descent(grad, side)
    h = np.swapaxes(sd, 1, 2).astype(np.float64) @ sd.astype(np.float64)
    scale = np.trace(h, axis1=1, axis2=2)[:, None, None] * 1e-6 + 1e-6
    h_inv = np.linalg.inv(h + scale * np.eye(6)).astype(np.float32)
    tc = t - t.mean(1, keepdims=True)
    return AffineTemplates(side, tc, (np.linalg.norm(tc, axis=1) + 1e-6).astype(np.float32), grad, h_inv, eye)


def refine(tpl: AffineTemplates, image: np.ndarray, uv: np.ndarray, iterations: int = 6,
           min_ncc: float = 0.8) -> tuple[np.ndarray, np.ndarray]:
    """Refine the warps of all templates in ``image`` starting at positions ``uv`` (N,2) and their current A.

    Returns the positions (N,2) and a mask of tracks whose warp converged with a normalised cross-correlation of
    at least ``min_ncc`` between template and warped patch; A is updated for those (unchanged for the others)."""
    n = len(tpl)
    t = np.asarray(uv, np.float32).reshape(-1, 2).copy()
    if n == 0:
        return t, np.zeros(0, bool)
    grid = _grid(tpl.side)
    A = tpl.A
    Tc, norms, h_inv = tpl.values, tpl.norms, tpl.h_inv
    Tn2 = norms ** 2
    sd = _steepest_descent(tpl.grad, tpl.side)
    eye2 = np.eye(2, dtype=np.float32)
    step = np.full(n, np.inf, np.float32)
    for _ in range(iterations):
        P = _sample(image, t, A, grid)
        # brightness: P ~ gain * T + offset, by least squares per patch, then compare in the template's units
        Pc = P - P.mean(1, keepdims=True)
        gain = np.einsum("nk,nk->n", Pc, Tc) / Tn2
        gain = np.where(gain > 1e-3, gain, 1.0).astype(np.float32)
        r = Pc / gain[:, None] - Tc
        dp = (h_inv @ (r[:, None, :] @ sd).transpose(0, 2, 1))[:, :, 0]  # (N, 6)
        # inverse compositional: W(x) <- W(W_dp^-1(x)); W_dp(x) = (I + D) x + d
        M = np.linalg.inv(eye2 + dp[:, :4].reshape(n, 2, 2))
        AM = A @ M
        t = t - (AM @ dp[:, 4:, None])[:, :, 0]
        A = AM
        step = np.linalg.norm(dp[:, 4:], axis=1)
        if step.max() < 0.01:
            break
    P = _sample(image, t, A, grid)
    Pc = P - P.mean(1, keepdims=True)
    ncc = np.einsum("nk,nk->n", Pc, Tc) / (np.linalg.norm(Pc, axis=1) * norms + 1e-6)
    ok = np.all(np.isfinite(t), 1) & (step < 0.1) & (ncc >= min_ncc)
    tpl.set_A(ok, A[ok])
    return t, ok


def warp_is_sane(A: np.ndarray, max_scale_change: float) -> np.ndarray:
    """(N,) mask of warps whose singular values stay within a factor ``max_scale_change`` of 1 (beyond, the
    template is too unlike the feature's look now: start a new one)."""
    s = np.linalg.svd(A, compute_uv=False)
    return (s.max(1) <= max_scale_change) & (s.min(1) >= 1.0 / max_scale_change)
