"""A bag of binary words for ORB descriptors (256-bit, as (N, 32) uint8 rows).

The vocabulary is a two-level tree of binary centres found by k-majority clustering (k-means under the
Hamming distance, where a centre is the bitwise majority of its members). A descriptor descends to the
nearest of ``k1`` top centres, then to the nearest of that branch's ``k2`` leaves: its *word*. A keyframe's
bag is the tf-idf weighted histogram of its words, L1-normalised; two bags are compared by the L1 score
``s = 1 - 0.5 * |a - b|_1`` (1: same histogram, 0: no word in common).

Vocabularies are built by ``tools/build_vocabulary.py`` and stored as ``.npz`` (centres, idf, provenance).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

DEFAULT_PATH = Path(__file__).resolve().parent / "data" / "orb_vocabulary.npz"


def hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamming distances (N, K) int32 between binary descriptors a (N, B) and b (K, B), uint8 rows.

    Word by word (64-bit words when B is a multiple of 8), each an (N, K) XOR and popcount: no (N, K, B)
    temporary. 12x faster than a byte table for ORB's 32 bytes (240 x 1500: 40 -> 3.3 ms), which matters live,
    where the loop closer's matching shares the back end's process with the window solve."""
    a, b = np.ascontiguousarray(a, np.uint8), np.ascontiguousarray(b, np.uint8)
    if a.shape[1] % 8 == 0:
        a, b = a.view(np.uint64), b.view(np.uint64)
    d = np.zeros((len(a), len(b)), np.int32)
    for j in range(a.shape[1]):
        d += np.bitwise_count(np.bitwise_xor.outer(a[:, j], b[:, j]))
    return d


def majority(desc: np.ndarray) -> np.ndarray:
    """Bitwise majority (B,) uint8 of binary descriptors (N, B); ties give 0."""
    bits = np.unpackbits(desc, axis=1)
    return np.packbits(bits.sum(axis=0) * 2 > len(desc))


def k_majority(desc: np.ndarray, k: int, rng: np.random.Generator, iterations: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Cluster binary descriptors into ``k`` centres (k-means++ seeding, Hamming distance, majority update).

    Returns (centres (k', B) uint8, labels (N,)), k' = min(k, number of distinct descriptors)."""
    desc = np.ascontiguousarray(desc, np.uint8)
    k = min(k, len(np.unique(desc, axis=0)))
    centres = [desc[rng.integers(len(desc))]]
    d = hamming(desc, centres[0][None])[:, 0].astype(float)
    while len(centres) < k:
        p = d ** 2
        if p.sum() == 0:
            break
        centres.append(desc[rng.choice(len(desc), p=p / p.sum())])
        d = np.minimum(d, hamming(desc, centres[-1][None])[:, 0])
    C = np.array(centres, np.uint8)
    labels = np.full(len(desc), -1)
    for _ in range(iterations):
        new = np.argmin(hamming(desc, C), axis=1)
        if np.array_equal(new, labels):
            break
        labels = new
        for j in range(len(C)):
            members = desc[labels == j]
            if len(members):
                C[j] = majority(members)
    return C, labels


@dataclass
class Vocabulary:
    """Two-level binary vocabulary: ``top`` (k1, B) centres, ``leaves`` (k1, k2, B) (unused leaves repeat a
    valid one), ``idf`` (k1 * k2,) inverse document frequency weights; word id = branch * k2 + leaf."""

    top: np.ndarray
    leaves: np.ndarray
    idf: np.ndarray
    provenance: dict

    @property
    def size(self) -> int:
        return self.leaves.shape[0] * self.leaves.shape[1]

    def words(self, desc: np.ndarray) -> np.ndarray:
        """Word id (N,) int64 of each descriptor (N, B)."""
        desc = np.ascontiguousarray(desc, np.uint8).reshape(-1, self.top.shape[1])
        if len(desc) == 0:
            return np.zeros(0, np.int64)
        branch = np.argmin(hamming(desc, self.top), axis=1)
        x = np.bitwise_xor(desc[:, None, :], self.leaves[branch])  # (N, k2, B)
        leaf = np.argmin(np.bitwise_count(x).sum(axis=2, dtype=np.int32), axis=1)
        return branch.astype(np.int64) * self.leaves.shape[1] + leaf

    def bag(self, desc: np.ndarray) -> np.ndarray:
        """Dense tf-idf bag (size,) float32, L1-normalised (all zeros for no descriptors)."""
        w = self.words(desc)
        v = np.bincount(w, minlength=self.size).astype(np.float32) * self.idf
        s = v.sum()
        return v / s if s > 0 else v

    def save(self, path: str | Path) -> None:
        np.savez_compressed(path, top=self.top, leaves=self.leaves, idf=self.idf.astype(np.float32),
                            provenance=np.array(json.dumps(self.provenance)))

    @classmethod
    def load(cls, path: str | Path = DEFAULT_PATH) -> "Vocabulary":
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: vocabulary not found (build one with tools/build_vocabulary.py)")
        with np.load(path) as z:
            return cls(z["top"], z["leaves"], z["idf"].astype(np.float32), json.loads(str(z["provenance"])))


def l1_score(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """L1 similarity in [0, 1] of an L1-normalised bag ``a`` (V,) with one or many bags ``b`` (V,) or (K, V)."""
    return 1.0 - 0.5 * np.abs(np.asarray(b) - a).sum(axis=-1)


def train(descriptor_sets: list[np.ndarray], k1: int = 16, k2: int = 64, seed: int = 0,
          provenance: dict | None = None) -> Vocabulary:
    """Vocabulary from the descriptors of training images (one (N_i, B) array per image; an image is a
    'document' for the idf)."""
    rng = np.random.default_rng(seed)
    desc = np.concatenate([d for d in descriptor_sets if len(d)]).astype(np.uint8)
    top, labels = k_majority(desc, k1, rng)
    leaves = np.zeros((len(top), k2, desc.shape[1]), np.uint8)
    for j in range(len(top)):
        c, _ = k_majority(desc[labels == j], k2, rng)
        leaves[j, :len(c)] = c
        leaves[j, len(c):] = c[0]  # padding: never nearer than the real centre it copies
    voc = Vocabulary(top, leaves, np.ones(len(top) * k2, np.float32), dict(provenance or {}))
    docs = np.zeros(voc.size)
    for d in descriptor_sets:
        if len(d):
            docs[np.unique(voc.words(d))] += 1
    n = sum(1 for d in descriptor_sets if len(d))
    voc.idf = np.log(n / np.maximum(docs, 1.0)).astype(np.float32) * (docs > 0)
    return voc
