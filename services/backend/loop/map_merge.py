"""Where one saved map lies in another: place recognition and PnP of one map's keyframes against the other's.

:func:`align_maps` queries every keyframe of map ``b`` against a place database of map ``a``'s keyframes (bags of
words from their descriptors, the same vocabulary), verifies the best candidates by PnP of ``b``'s features
(stored in normalised coordinates, so no camera model is needed) against ``a``'s landmark positions, and turns
each verified match into a guess of ``T_ab`` (``b``'s frame in ``a``'s). The guess that most other guesses agree
with (within ``relocalise_agree_m`` / ``relocalise_agree_deg``) is chosen when at least ``relocalise_confirmations``
agree, and ``T_ab`` is the mean of the guesses that agree with it; the agreeing matches become the loop edges that tie the two maps in the merged one
(:func:`services.backend.loop.saved_map.concatenate`). Transport-free: ``sigmaslam map merge`` calls it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from services.backend.loop.config import LoopConfig
from services.backend.loop.place_recognition import PlaceDatabase
from services.backend.loop.guesses import agree, mean_pose
from services.backend.loop.saved_map import LOOP, SparseMap, SparseMapError
from services.backend.loop.verification import verify_pnp
from services.backend.loop.vocabulary import Vocabulary, l1_score
from shared.geometry import inv_T


@dataclass
class MapAlignment:
    T_ab: np.ndarray | None  # b's frame in a's (None: the maps share no verified place)
    links: list = field(default_factory=list)  # (key in a, key in b, T_a_b-keyframes, cov, LOOP) of agreeing matches
    queried: int = 0  # b's keyframes queried
    verified: int = 0  # verified matches (agreeing or not)
    agreeing: int = 0


def _cameras(m: SparseMap) -> tuple[np.ndarray, np.ndarray]:
    cams = m.meta.get("cameras")
    if not cams:
        raise SparseMapError("the map does not record its cameras (saved before maps carried them)")
    return np.array([c["T_SC"] for c in cams], float), np.array([c["focal_px"] for c in cams], float)


def align_maps(a: SparseMap, b: SparseMap, voc: Vocabulary, cfg: LoopConfig = LoopConfig(),
               progress=None) -> MapAlignment:
    """Find ``T_ab``; ``progress(done, total)`` is called now and then."""
    T_SC, focal = _cameras(b)
    if len(_cameras(a)[0]) != len(T_SC):
        raise SparseMapError("the two maps were made with rigs of different camera counts")
    db = PlaceDatabase(voc.size)
    feats_a = {}
    for i in range(len(a)):
        fs, p = a.features(i)
        if len(fs.landmark_ids) and np.isfinite(p[:, 0]).sum() >= cfg.min_inliers:
            feats_a[i] = (fs, p)
            db.add(i, 0, voc.bag(fs.descriptors))
    ident = [lambda xy: np.asarray(xy, float)] * len(T_SC)  # b's features are already normalised
    out = MapAlignment(None)
    guesses = []
    prev_bag = None
    for j in range(len(b)):
        if progress is not None and j % 50 == 0:
            progress(j, len(b))
        fs, _ = b.features(j, normalised=True)
        if len(fs.landmark_ids) < cfg.min_inliers:
            continue
        bag = voc.bag(fs.descriptors)
        ref = float(l1_score(bag, prev_bag)) if prev_bag is not None else None
        prev_bag = bag
        out.queried += 1
        for c in db.query(bag, 1, 0.0, cfg.min_score, 0.0, ref, 3 * cfg.max_candidates):
            fa, pa = feats_a[c.key]
            res = verify_pnp(fs, fa, pa, ident, T_SC, focal, cfg.sigma_px, cfg.max_hamming, cfg.ransac_px,
                             cfg.min_inliers, cfg.min_inlier_ratio, cfg.cov_inflation)
            if res.accepted:
                out.verified += 1
                guesses.append((res.T_WS @ inv_T(b.T_WS[j]), c.key, j, res))
                break
    if not guesses:
        return out
    support = [[g for g in guesses if agree(g[0], h[0], cfg)] for h in guesses]
    best = int(np.argmax([len(s) for s in support]))
    out.agreeing = len(support[best])
    if out.agreeing < max(1, cfg.relocalise_confirmations):
        return out
    out.T_ab = mean_pose([g[0] for g in support[best]])
    out.links = [(int(a.keys[i]), int(b.keys[j]), inv_T(a.T_WS[i]) @ res.T_WS, res.covariance, LOOP)
                 for _, i, j, res in support[best]]
    return out
