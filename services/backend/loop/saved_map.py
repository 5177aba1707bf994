"""The sparse half of a saved map: what relocalisation needs, written by the back end, read without the transport.

A :class:`SparseMap` holds, in the map's world frame ``W`` (gravity along -z, as every estimator frame):

- keyframes: id, stamp, body pose ``T_WS``, the session they came from;
- per keyframe its features (landmark id, camera, distorted pixel, ORB descriptor) and the position of each
  feature's landmark where the estimator had one (NaN where not): the loop closer's PnP verification reads these;
- the pose graph's edges (odometry between consecutive keyframes and accepted loops: relative pose, covariance);
- the rig: each camera's ``T_SC`` and focal length (meta["cameras"]), so that a map can be matched against another
  (``sigmaslam map merge``) without the calibration files;
- provenance: the format tag, the vocabulary it was made with (a different vocabulary cannot query it), the
  sessions (source dataset, keyframe count, creation time) and how often each session was aligned to the map.

The place-recognition database is not stored: it is rebuilt from the descriptors with the vocabulary on load
(:meth:`services.backend.loop.loop_closer.LoopCloser.load_prior`), which costs milliseconds per keyframe and keeps
the file independent of the database's layout. Covisibility is the features' landmark ids. One ``.npz``, written
atomically (shared/map_folder.py): a process killed mid-save leaves the previous complete file.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import time
from pathlib import Path

import numpy as np

from services.backend.loop.verification import FeatureSet
from shared.map_folder import atomic_write

FORMAT = "sigmaslam-sparse-map/1"
ODOMETRY, LOOP = 0, 1  # edge kinds


class SparseMapError(ValueError):
    """A sparse map file that cannot be read, or maps that cannot be combined."""


@dataclasses.dataclass
class SparseMap:
    keys: np.ndarray  # (K,) int64 keyframe ids, unique
    stamps_ns: np.ndarray  # (K,) int64
    T_WS: np.ndarray  # (K,4,4) body poses in the map frame
    session: np.ndarray  # (K,) int32 index into meta["sessions"]
    feat_offsets: np.ndarray  # (K+1,) int64: keyframe i's features are rows feat_offsets[i]:feat_offsets[i+1]
    landmark_ids: np.ndarray  # (F,) int64
    camera_index: np.ndarray  # (F,) int64
    uv: np.ndarray  # (F,2) float32 distorted pixels
    xy: np.ndarray  # (F,2) float64 the same features in normalised coordinates (undistorted): usable as queries
    #                 without the camera model (sigmaslam map merge); meta["cameras"] has each camera's T_SC, focal
    descriptors: np.ndarray  # (F,32) uint8
    p_W: np.ndarray  # (F,3) float64 landmark positions in the map frame, NaN where unknown
    edges: np.ndarray  # (E,2) int64 (from key, to key)
    edge_T: np.ndarray  # (E,4,4) relative pose T_from_to
    edge_cov: np.ndarray  # (E,6,6) its covariance, gtsam Pose3 tangent order [rot, trans]
    edge_kind: np.ndarray  # (E,) int8: ODOMETRY or LOOP
    meta: dict = dataclasses.field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.keys)

    def features(self, i: int, normalised: bool = False) -> tuple[FeatureSet, np.ndarray]:
        """Keyframe ``i``'s (row, not id) features and their landmark positions (n,3); with ``normalised`` the
        features' ``uv`` are the normalised coordinates ``xy``."""
        a, b = int(self.feat_offsets[i]), int(self.feat_offsets[i + 1])
        uv = self.xy[a:b] if normalised else self.uv[a:b].astype(float)
        return FeatureSet(self.landmark_ids[a:b], self.camera_index[a:b], uv, self.descriptors[a:b]), self.p_W[a:b]

    def summary(self) -> dict:
        """Counts and extent for ``sigmaslam map info``."""
        known = np.all(np.isfinite(self.p_W), axis=1)
        p = self.T_WS[:, :3, 3] if len(self) else np.zeros((0, 3))
        return {"format": self.meta.get("format", FORMAT), "keyframes": len(self),
                "keyframes_with_features": int(np.sum(np.diff(self.feat_offsets) > 0)),
                "features": int(len(self.landmark_ids)),
                "landmarks": int(len(np.unique(self.landmark_ids[known]))) if known.any() else 0,
                "odometry_edges": int(np.sum(self.edge_kind == ODOMETRY)),
                "loop_edges": int(np.sum(self.edge_kind == LOOP)),
                "extent_m": [[float(v) for v in p.min(0)], [float(v) for v in p.max(0)]] if len(p) else None,
                "path_length_m": float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum()) if len(p) > 1 else 0.0,
                "vocabulary": self.meta.get("vocabulary", {}), "sessions": self.meta.get("sessions", [])}


def vocabulary_id(voc) -> dict:
    """What identifies a vocabulary (services/backend/loop/vocabulary.py): its size and a hash of its words."""
    h = hashlib.sha1()
    for a in (voc.top, voc.leaves, voc.idf):
        h.update(np.ascontiguousarray(a).tobytes())
    return {"size": int(voc.size), "sha1": h.hexdigest()[:16]}


def empty_map(meta: dict | None = None) -> SparseMap:
    return SparseMap(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 4, 4)), np.zeros(0, np.int32),
                     np.zeros(1, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2), np.float32),
                     np.zeros((0, 2)), np.zeros((0, 32), np.uint8), np.zeros((0, 3)), np.zeros((0, 2), np.int64), np.zeros((0, 4, 4)),
                     np.zeros((0, 6, 6)), np.zeros(0, np.int8), dict(meta or {}))


def build_map(keyframes: list[tuple[int, int, np.ndarray, FeatureSet | None, np.ndarray | None, np.ndarray | None]],
              edges: list[tuple[int, int, np.ndarray, np.ndarray, int]], meta: dict, session: int = 0) -> SparseMap:
    """A map from keyframes ``(key, stamp, T_WS, features or None, p_W or None, normalised xy or None)`` and edges
    ``(from, to, T, cov, kind)`` (edges to keys that are not keyframes are dropped)."""
    keys = [int(k[0]) for k in keyframes]
    if len(set(keys)) != len(keys):
        raise SparseMapError("duplicate keyframe ids")
    feats = [k[3] for k in keyframes]
    n = [0 if f is None else len(f.landmark_ids) for f in feats]
    cat = (lambda get, shape, dtype: np.concatenate([np.asarray(get(f, p, xy), dtype).reshape(shape)
                                                     for (_, _, _, f, p, xy) in keyframes if f is not None])
           if any(n) else np.zeros((0, *shape[1:]), dtype))
    ks = set(keys)
    edges = [e for e in edges if int(e[0]) in ks and int(e[1]) in ks]
    return SparseMap(
        keys=np.array(keys, np.int64), stamps_ns=np.array([int(k[1]) for k in keyframes], np.int64),
        T_WS=np.array([np.asarray(k[2], float) for k in keyframes]).reshape(-1, 4, 4),
        session=np.full(len(keys), session, np.int32), feat_offsets=np.r_[0, np.cumsum(n)].astype(np.int64),
        landmark_ids=cat(lambda f, p, xy: f.landmark_ids, (-1,), np.int64),
        camera_index=cat(lambda f, p, xy: f.camera_index, (-1,), np.int64),
        uv=cat(lambda f, p, xy: f.uv, (-1, 2), np.float32), xy=cat(lambda f, p, xy: xy, (-1, 2), np.float64),
        descriptors=cat(lambda f, p, xy: f.descriptors, (-1, 32), np.uint8),
        p_W=cat(lambda f, p, xy: p, (-1, 3), np.float64),
        edges=np.array([(int(e[0]), int(e[1])) for e in edges], np.int64).reshape(-1, 2),
        edge_T=np.array([np.asarray(e[2], float) for e in edges]).reshape(-1, 4, 4),
        edge_cov=np.array([np.asarray(e[3], float) for e in edges]).reshape(-1, 6, 6),
        edge_kind=np.array([int(e[4]) for e in edges], np.int8), meta=dict(meta))


def concatenate(a: SparseMap, b: SparseMap, T_ab: np.ndarray = np.eye(4), links: list = ()) -> SparseMap:
    """``a`` followed by ``b`` moved into ``a``'s frame by ``T_ab`` (poses, landmark positions); ``b``'s keyframe
    and landmark ids are shifted past ``a``'s so that nothing collides, its sessions appended. ``links``: extra
    edges ``(key in a, key in b (before the shift), T, cov, kind)`` (the places the two share)."""
    if a.meta.get("vocabulary") and b.meta.get("vocabulary") and a.meta["vocabulary"] != b.meta["vocabulary"]:
        raise SparseMapError("the two maps were made with different vocabularies")
    T_ab = np.asarray(T_ab, float)
    key_shift = int(a.keys.max()) + 1 if len(a) else 0
    lm_shift = int(a.landmark_ids.max()) + 1 if len(a.landmark_ids) else 0
    p_b = b.p_W @ T_ab[:3, :3].T + T_ab[:3, 3]
    sessions = list(a.meta.get("sessions", [])) + list(b.meta.get("sessions", []))
    link = [(int(k_a), int(k_b) + key_shift, T, c, kind) for k_a, k_b, T, c, kind in links]
    meta = {**a.meta, "sessions": sessions}
    return SparseMap(
        keys=np.r_[a.keys, b.keys + key_shift], stamps_ns=np.r_[a.stamps_ns, b.stamps_ns],
        T_WS=np.concatenate([a.T_WS, np.einsum("ij,njk->nik", T_ab, b.T_WS)]),
        session=np.r_[a.session, b.session + len(a.meta.get("sessions", []))].astype(np.int32),
        feat_offsets=np.r_[a.feat_offsets, b.feat_offsets[1:] + a.feat_offsets[-1]].astype(np.int64),
        landmark_ids=np.r_[a.landmark_ids, b.landmark_ids + lm_shift], camera_index=np.r_[a.camera_index, b.camera_index],
        uv=np.concatenate([a.uv, b.uv]), xy=np.concatenate([a.xy, b.xy]), descriptors=np.concatenate([a.descriptors, b.descriptors]),
        p_W=np.concatenate([a.p_W, p_b]),
        edges=np.concatenate([a.edges, b.edges + key_shift, np.array([e[:2] for e in link], np.int64).reshape(-1, 2)]),
        edge_T=np.concatenate([a.edge_T, b.edge_T, np.array([e[2] for e in link]).reshape(-1, 4, 4)]),
        edge_cov=np.concatenate([a.edge_cov, b.edge_cov, np.array([e[3] for e in link]).reshape(-1, 6, 6)]),
        edge_kind=np.r_[a.edge_kind, b.edge_kind, np.array([e[4] for e in link], np.int8)].astype(np.int8), meta=meta)


_ARRAYS = ("keys", "stamps_ns", "T_WS", "session", "feat_offsets", "landmark_ids", "camera_index", "uv", "xy",
           "descriptors",
           "p_W", "edges", "edge_T", "edge_cov", "edge_kind")


def save_sparse(m: SparseMap, path: str | Path) -> Path:
    """Write ``m`` to ``path`` (.npz) atomically."""
    meta = {**m.meta, "format": FORMAT, "saved_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
    arrays = {k: getattr(m, k) for k in _ARRAYS}
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    return atomic_write(path, lambda fh: np.savez(fh, **arrays))


def load_sparse(path: str | Path) -> SparseMap:
    """Read a file written by :func:`save_sparse`; a clear :class:`SparseMapError` for anything else."""
    try:
        with np.load(path) as z:
            data = {k: z[k] for k in z.files}
        meta = json.loads(bytes(data.pop("meta")).decode())
    except FileNotFoundError:
        raise
    except (OSError, ValueError, KeyError) as exc:
        raise SparseMapError(f"{path}: not a readable sparse map ({exc})") from exc
    if meta.get("format") != FORMAT:
        raise SparseMapError(f"{path}: format {meta.get('format')!r}, expected {FORMAT!r}")
    missing = [k for k in _ARRAYS if k not in data]
    if missing:
        raise SparseMapError(f"{path}: arrays missing: {', '.join(missing)}")
    m = SparseMap(**{k: data[k] for k in _ARRAYS}, meta=meta)
    if len(m.feat_offsets) != len(m) + 1 or m.feat_offsets[-1] != len(m.landmark_ids):
        raise SparseMapError(f"{path}: feature offsets do not match the features")
    return m
