"""Multi-camera KLT tracker: one landmark id per physical point across time and cameras.

Per frame, for each camera: track the previous features with KLT (starting where the gyro-integrated
rotation puts them), forward-backward check, fundamental-matrix RANSAC against the previous frame; then
drop cross-camera observations of one landmark that violate the rig's epipolar geometry. New corners are
detected in the free grid cells of each camera and matched into every overlapping camera (KLT from a
guess at a nominal depth, forward-backward check, epipolar distance and positive depth from the
extrinsics), so that a landmark seen by two cameras carries the same id. A frame is a keyframe when the
share of the last keyframe's landmarks still tracked falls, the rotation-compensated parallax grows, or
time passes; ORB descriptors of the tracked features are kept per keyframe (for loop closure).
"""

from __future__ import annotations

import collections
import dataclasses
from dataclasses import dataclass, field

import cv2
import numpy as np

from services.frontend import affine_klt, klt
from services.frontend.frames import FrontendInputError, KeyframeDescriptors, TrackerOutput
from services.frontend.klt import gain_matched, normalised_gain
from services.frontend.config import FrontendConfig
from services.frontend.detection import detect_spread
from shared.lookup_camera import LookupCamera
from services.frontend.epipolar import cross_camera_check, overlapping_pairs, ransac_inliers
from services.frontend.keyframe_features import describe_keyframe
from shared.camera import CameraCalib
from shared.geometry import inv_T


@dataclass
class _CameraState:
    ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    uv: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.float32))
    vel: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.float32))  # [px/s] since the last frame
    image: np.ndarray | None = None
    templates: affine_klt.AffineTemplates | None = None  # per track, with klt_affine

    def keep(self, mask: np.ndarray) -> None:
        self.ids, self.uv, self.vel = self.ids[mask], self.uv[mask], self.vel[mask]
        if self.templates is not None:
            self.templates.keep(mask)

    def append(self, ids: np.ndarray, uv: np.ndarray) -> None:
        """New features (no velocity yet), first seen in ``image``."""
        self.ids = np.concatenate([self.ids, ids.astype(np.int64)])
        self.uv = np.concatenate([self.uv, uv.astype(np.float32)]).reshape(-1, 2)
        self.vel = np.concatenate([self.vel, np.zeros((len(ids), 2), np.float32)])
        if self.templates is not None:
            self.templates.append(affine_klt.make_templates(self.image, uv, self.templates.side))


class MultiCameraTracker:
    """Feed :meth:`process` with each frame's images (in rig order) and the body rotation since the last frame."""

    def __init__(self, cfg: FrontendConfig, cameras: list[CameraCalib], first_landmark_id: int = 0) -> None:
        """``first_landmark_id``: ids are handed out from here on (a restarted frontend starts a fresh range so
        that the back end never confuses its new tracks with the old ones)."""
        if not cameras:
            raise ValueError("the frontend needs at least one camera")
        self.cfg = cfg
        # the tracker works on copies whose unprojection is a table lookup
        self.cameras = [dataclasses.replace(c, camera=LookupCamera(c.camera)) for c in cameras]
        self._cams = [_CameraState() for _ in cameras]
        if cfg.klt_affine:
            for st in self._cams:
                st.templates = affine_klt.AffineTemplates.empty(cfg.affine_window_px | 1)
        self._pairs = overlapping_pairs(self.cameras, cfg.min_view_overlap_cos)
        self._R_SC = [np.asarray(c.T_SC, float)[:3, :3] for c in cameras]
        self._next_id = int(first_landmark_id)
        self._deferred: list[np.ndarray] | None = None  # images of a frame whose detection waits (finish_frame)
        self._deferred_kf: tuple[int, list[np.ndarray], collections.Counter] | None = None  # a keyframe's work waits (finish_keyframe)
        self._last_stamp: int | None = None
        self._kf_id = -1
        self._kf_stamp: int | None = None
        self._kf_obs: list[tuple[np.ndarray, np.ndarray]] = []  # per camera (ids, uv) at the last keyframe
        self._R_S_kf_cur = np.eye(3)
        self.time_offset_s = 0.0  # published tracks are moved by -offset x their image velocity (set_time_offset)
        self._orb = cv2.ORB_create(nfeatures=1, edgeThreshold=19, patchSize=31) if cfg.orb_descriptors else None
        self.keyframe_descriptors: collections.deque[KeyframeDescriptors] = collections.deque(maxlen=cfg.keyframe_store)
        self.totals: collections.Counter = collections.Counter()

    def set_extrinsics(self, T_SC: np.ndarray) -> None:
        """Use ``T_SC`` (C,4,4, rig order) from now on: the back end's refined extrinsics (cross-camera epipolar
        checks, stereo triangulation of new points and the gyro's rotation prior use them)."""
        T = np.asarray(T_SC, float)
        if T.shape != (len(self.cameras), 4, 4):
            raise FrontendInputError(f"extrinsics of shape {T.shape} for a rig of {len(self.cameras)} cameras")
        self.cameras = [dataclasses.replace(c, T_SC=t.copy()) for c, t in zip(self.cameras, T)]
        self._R_SC = [t[:3, :3].copy() for t in T]
        self._pairs = overlapping_pairs(self.cameras, self.cfg.min_view_overlap_cos)

    def set_time_offset(self, offset_s: float) -> None:
        """The back end's camera-IMU offset estimate (an image stamped t was taken at IMU time t + offset): from now
        on each published track is moved by -offset x its image velocity, to where it was at the stamp."""
        if not np.isfinite(offset_s):
            raise FrontendInputError(f"time offset {offset_s} s is not finite")
        self.time_offset_s = float(offset_s)

    # ------------------------------------------------------------------ helpers
    def _check(self, stamp_ns: int, images) -> list[np.ndarray]:
        if len(images) != len(self.cameras):
            raise FrontendInputError(f"{len(images)} images for a rig of {len(self.cameras)} cameras")
        out = []
        for img, c in zip(images, self.cameras):
            img = np.asarray(img)
            if img.dtype != np.uint8 or img.shape != (c.camera.height, c.camera.width):
                raise FrontendInputError(f"{c.name}: image {img.shape} {img.dtype}, expected "
                                         f"({c.camera.height}, {c.camera.width}) uint8")
            out.append(np.ascontiguousarray(img))
        if self._last_stamp is not None and stamp_ns <= self._last_stamp:
            raise FrontendInputError(f"frame stamp {stamp_ns} ns is not after the previous {self._last_stamp} ns")
        return out

    def _R_C1C0(self, i: int, R_S0S1: np.ndarray) -> np.ndarray:
        """Rotation taking camera i's rays at the earlier time into camera i at the later time."""
        R = self._R_SC[i]
        return (R.T @ R_S0S1 @ R).T

    def _new_ids(self, n: int) -> np.ndarray:
        ids = np.arange(self._next_id, self._next_id + n, dtype=np.int64)
        self._next_id += n
        return ids

    # ------------------------------------------------------------------ per frame
    def process(self, stamp_ns: int, images, R_S_prev_cur: np.ndarray | None = None,
                may_defer: bool = False, may_defer_keyframe: bool = False) -> TrackerOutput:
        """Track, reject, detect and match for one frame; ``R_S_prev_cur`` = R_S(prev)S(cur) from the gyro.

        With ``may_defer``, a frame that is not a keyframe is returned with its tracked features only: detecting and
        matching new ones waits for :meth:`finish_frame` (called after the output is sent, off the latency path;
        else at the start of the next frame). The tracker's state is the same either way; only that frame's output
        lacks the new features, which the next frames carry as tracked ones (a window that takes keyframes only
        never sees the difference). With ``may_defer_keyframe`` a keyframe too (``is_keyframe`` set): its complete
        output comes from :meth:`finish_keyframe`, after the state its tracked features give is sent."""
        self.finish_frame()
        self.finish_keyframe()
        images = self._check(stamp_ns, images)
        cfg = self.cfg
        dt_s = 0.0 if self._last_stamp is None else (int(stamp_ns) - self._last_stamp) * 1e-9
        if cfg.normalise_gain:
            images = [normalised_gain(im, cfg.normalised_mean_dn) for im in images]
        counts: collections.Counter = collections.Counter()
        use_prior = cfg.use_gyro_prior and R_S_prev_cur is not None
        R_rel = np.asarray(R_S_prev_cur, float) if R_S_prev_cur is not None else np.eye(3)
        for i, (cam, st) in enumerate(zip(self.cameras, self._cams)):
            if st.image is not None and len(st.ids):
                self._track_temporal(i, cam, st, images[i], R_rel if use_prior else None, counts, dt_s)
            st.image = images[i]
        self._check_cross_camera(counts)
        self._R_S_kf_cur = self._R_S_kf_cur @ R_rel
        # new features change the decision only when the last keyframe had none (see _keyframe_decision)
        decided = bool(self._kf_obs) and any(len(ids) for ids, _ in self._kf_obs)
        is_kf = self._keyframe_decision(stamp_ns, counts) if decided else False
        self._last_stamp = int(stamp_ns)
        if may_defer and decided and not is_kf:
            self._deferred = images
            counts["detection_deferred"] += 1
            return self._output(stamp_ns, False, counts)
        if may_defer_keyframe and decided and is_kf:
            counts["keyframe_deferred"] += 1
            self._deferred_kf = (int(stamp_ns), images, counts)  # counted once, complete, by finish_keyframe
            return self._output(stamp_ns, True, counts, keyframe_id=self._kf_id + 1, count=False)
        self._detect_and_match(images, counts)
        if not decided:
            is_kf = self._keyframe_decision(stamp_ns, counts)
        if is_kf:
            self._start_keyframe(stamp_ns, images, counts)
        return self._output(stamp_ns, is_kf, counts)

    @property
    def keyframe_pending(self) -> bool:
        return self._deferred_kf is not None  # process() left the last keyframe's work for finish_keyframe()

    def finish_keyframe(self) -> TrackerOutput | None:
        """The work on a keyframe :meth:`process` returned early; its complete output (None: nothing waited)."""
        pending, self._deferred_kf = self._deferred_kf, None
        if pending is None:
            return None
        stamp_ns, images, counts = pending
        self._detect_and_match(images, counts)
        self._start_keyframe(stamp_ns, images, counts)
        return self._output(stamp_ns, True, counts)

    @property
    def detection_pending(self) -> bool:
        """Whether :meth:`process` left the last frame's detection for :meth:`finish_frame`."""
        return self._deferred is not None

    def skip_deferred(self) -> None:
        """Leave out the detection :meth:`process` deferred for the last frame (counted as ``detection_skipped``);
        the next keyframe detects in any case."""
        if self._deferred is not None:
            self._deferred = None
            self.totals["detection_skipped"] += 1

    def finish_frame(self) -> int:
        """Detect and match new features in the last frame if :meth:`process` deferred it; their count."""
        images, self._deferred = self._deferred, None
        if images is None:
            return 0
        counts: collections.Counter = collections.Counter()
        self._detect_and_match(images, counts)
        self.totals.update(counts)
        return counts["detected"]

    def _detect_and_match(self, images: list[np.ndarray], counts) -> None:
        cfg = self.cfg
        for i, (cam, st) in enumerate(zip(self.cameras, self._cams)):
            new_uv = detect_spread(images[i], st.uv, cfg.max_features_per_camera, cfg.grid_cols, cfg.grid_rows,
                                   cfg.min_distance_px, cfg.fast_threshold, cfg.border_px)
            if len(new_uv):
                ids = self._new_ids(len(new_uv))
                st.append(ids, new_uv)
                counts["detected"] += len(new_uv)
                self._match_into_others(i, ids, new_uv, counts)

    def _output(self, stamp_ns: int, is_kf: bool, counts, keyframe_id: int | None = None,
                count: bool = True) -> TrackerOutput:
        ids = np.concatenate([st.ids for st in self._cams])
        cam_idx = np.concatenate([np.full(len(st.ids), i, np.int16) for i, st in enumerate(self._cams)])
        uv = np.concatenate([st.uv for st in self._cams]).reshape(-1, 2).astype(np.float32)
        if self.time_offset_s:
            uv = (uv - self.time_offset_s * np.concatenate([st.vel for st in self._cams]).reshape(-1, 2)).astype(np.float32)
        counts["observations"] = len(ids)
        counts["landmarks"] = len(np.unique(ids))
        if count:
            self.totals.update(counts)
        kf_id = (self._kf_id if keyframe_id is None else keyframe_id) if is_kf else -1
        return TrackerOutput(int(stamp_ns), ids, cam_idx, uv, is_kf, kf_id, dict(counts))

    def _track_temporal(self, i: int, cam: CameraCalib, st: _CameraState, image, R_rel, counts, dt_s: float) -> None:
        cfg = self.cfg
        model = cam.camera
        guess = None if R_rel is None else klt.predict_rotated(model, st.uv, self._R_C1C0(i, R_rel))
        uv1, ok = klt.track(*self._klt_pair(st.image, image), st.uv, guess, cfg.klt_window_px, cfg.klt_levels,
                            cfg.klt_iterations, cfg.fb_max_error_px, model.size, cfg.fb_levels)
        counts["lost_klt"] += int((~ok).sum())
        uv0 = st.uv[ok]
        uv1 = uv1[ok]
        st.keep(ok)
        if st.templates is not None and len(uv1) and not cfg.affine_keyframes_only:
            uv1 = self._refine_affine(st, image, uv1, counts)
        # RANSAC only where the views differ by more than a rotation (else the epipolar geometry is degenerate):
        # frame to frame, and against the last keyframe (more parallax, and slow independent motion adds up)
        comp = uv0 if guess is None else guess[ok]
        keep = self._ransac(model, uv0, uv1, comp)
        if self._kf_obs and self._kf_stamp is not None:
            kf_ids, kf_uv = self._kf_obs[i]
            common, ia, ib = np.intersect1d(st.ids, kf_ids, assume_unique=True, return_indices=True)
            if len(common) >= 8:
                pred = klt.predict_rotated(model, kf_uv[ib], self._R_C1C0(i, self._R_S_kf_cur @ (
                    R_rel if R_rel is not None else np.eye(3))))
                keep[ia] &= self._ransac(model, kf_uv[ib], uv1[ia], pred)
        counts["rejected_ransac"] += int((~keep).sum())
        st.keep(keep)
        uv1 = uv1[keep]
        st.vel = ((uv1 - uv0[keep]) / dt_s if dt_s > 0 else np.zeros_like(uv1)).astype(np.float32)
        st.uv = uv1.astype(np.float32)
        counts["tracked"] += len(st.ids)

    def _refine_affine(self, st: _CameraState, image: np.ndarray, uv1: np.ndarray, counts) -> np.ndarray:
        """Frame-to-frame positions ``uv1`` refined against each track's first patch (affine_klt); a track whose
        refinement fails, moves too far or whose warp has grown too unlike the identity keeps its KLT position and
        starts a new template there."""
        cfg = self.cfg
        ref, good = affine_klt.refine(st.templates, image, uv1, cfg.affine_iterations, cfg.affine_min_ncc)
        good &= np.linalg.norm(ref - uv1, axis=1) <= cfg.affine_max_move_px
        good &= affine_klt.warp_is_sane(st.templates.A, cfg.affine_max_scale_change)
        out = np.where(good[:, None], ref, uv1).astype(np.float32)
        restart = np.flatnonzero(~good)
        if len(restart):
            st.templates.replace(restart, affine_klt.make_templates(image, out[restart], st.templates.side))
        counts["affine_refined"] += int(good.sum())
        counts["affine_restarted"] += len(restart)
        return out

    def _klt_pair(self, a: np.ndarray, b: np.ndarray, cross: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """The images KLT tracks between: gain-matched under ``match_gain``, or ``match_gain_cross`` between cameras."""
        cfg = self.cfg
        return gain_matched(a, b) if cfg.match_gain or (cross and cfg.match_gain_cross) else (a, b)

    def _ransac(self, model, uv0: np.ndarray, uv1: np.ndarray, uv0_rotated: np.ndarray) -> np.ndarray:
        cfg = self.cfg
        if len(uv1) < 8 or np.median(np.linalg.norm(uv1 - uv0_rotated, axis=1)) < cfg.ransac_min_flow_px:
            return np.ones(len(uv1), bool)
        return ransac_inliers(model, uv0, uv1, cfg.ransac_threshold_px, cfg.ransac_confidence)

    def _check_cross_camera(self, counts) -> None:
        """Drop the later camera's observation of a landmark whose two views violate the rig geometry."""
        for i, j in self._pairs:
            if i > j:
                continue
            a, b = self._cams[i], self._cams[j]
            common, ia, ib = np.intersect1d(a.ids, b.ids, assume_unique=True, return_indices=True)
            if len(common) == 0:
                continue
            geometric, ok = self._cross_ok(i, j, a.uv[ia], b.uv[ib], counts)
            if not ok.all():
                keep = np.ones(len(b.ids), bool)
                keep[ib[~ok]] = False
                b.keep(keep)
                counts["rejected_epipolar"] += int((~geometric).sum())

    def _cross_ok(self, i: int, j: int, uv_i: np.ndarray, uv_j: np.ndarray, counts,
                  pair: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Masks of camera i / camera j observations of the same landmarks: those that agree with the rig geometry
        (epipolar distance, depth), and those that also agree, with ``stereo_recheck_px``, with a fresh small-window
        match of camera i's pixel into camera j started at camera j's pixel. The two cameras' tracks of a landmark
        can drift apart along the epipolar line, and a match on an occlusion edge depends on the window: neither
        shows in the epipolar distance, and both bias the disparity towards the nearer surface. ``pair``: the two
        images as the cross-camera KLT sees them, when the caller has them already."""
        cfg = self.cfg
        geometric = cross_camera_check(self.cameras[i], self.cameras[j], uv_i, uv_j, cfg.epipolar_max_px,
                                       cfg.stereo_min_depth_m)
        if cfg.stereo_recheck_px <= 0 or not geometric.any():
            return geometric, geometric
        sel = np.flatnonzero(geometric)
        if pair is None:
            pair = self._klt_pair(self._cams[i].image, self._cams[j].image, cross=True)
        fresh, agree = klt.track(*pair, uv_i[sel], uv_j[sel], cfg.stereo_recheck_window_px, 0, cfg.klt_iterations,
                                 cfg.fb_max_error_px, self.cameras[j].camera.size, 0)
        agree &= np.linalg.norm(fresh - uv_j[sel], axis=1) <= cfg.stereo_recheck_px
        ok = geometric.copy()
        ok[sel] = agree
        counts["rejected_stereo_recheck"] += int((~agree).sum())
        return geometric, ok

    def _match_into_others(self, i: int, ids: np.ndarray, uv_i: np.ndarray, counts) -> None:
        cfg = self.cfg
        cam_i = self.cameras[i]
        for a, j in self._pairs:
            if a != i:
                continue
            cam_j, st_j = self.cameras[j], self._cams[j]
            T_CjCi = inv_T(cam_j.T_SC) @ cam_i.T_SC
            p_Cj = cam_i.camera.unproject(uv_i) * cfg.stereo_init_depth_m @ T_CjCi[:3, :3].T + T_CjCi[:3, 3]
            guess, vis = cam_j.camera.project(p_Cj)
            if not vis.any():
                continue
            sel = np.flatnonzero(vis)
            pair = self._klt_pair(self._cams[i].image, st_j.image, cross=True)
            uv_j, ok = klt.track(*pair, uv_i[sel], guess[sel], cfg.klt_window_px, cfg.klt_levels, cfg.klt_iterations,
                                 cfg.fb_max_error_px, cam_j.camera.size, cfg.fb_levels)
            ok[ok] = self._cross_ok(i, j, uv_i[sel][ok], uv_j[ok], counts, pair)[1]
            if len(st_j.uv) and ok.any():  # not on top of a feature camera j already tracks
                d2 = np.min(((uv_j[:, None, :] - st_j.uv[None, :, :]) ** 2).sum(-1), axis=1)
                ok &= d2 > (0.5 * cfg.min_distance_px) ** 2
            ok &= ~np.isin(ids[sel], st_j.ids)
            st_j.append(ids[sel][ok], uv_j[ok])
            counts["cross_matched"] += int(ok.sum())

    # ------------------------------------------------------------------ keyframes
    def _keyframe_decision(self, stamp_ns: int, counts) -> bool:
        cfg = self.cfg
        if self._kf_stamp is None:
            return True
        if stamp_ns - self._kf_stamp >= cfg.kf_max_interval_s * 1e9:
            counts["kf_time"] += 1
            return True
        kf_ids = np.unique(np.concatenate([ids for ids, _ in self._kf_obs])) if self._kf_obs else np.zeros(0, np.int64)
        now_ids = np.unique(np.concatenate([st.ids for st in self._cams]))
        if len(kf_ids) == 0:
            return len(now_ids) > 0
        if np.isin(kf_ids, now_ids).mean() < cfg.kf_min_track_ratio:
            counts["kf_track_ratio"] += 1
            return True
        parallax = []
        for i, (st, (ids0, uv0)) in enumerate(zip(self._cams, self._kf_obs)):
            common, i0, i1 = np.intersect1d(ids0, st.ids, assume_unique=True, return_indices=True)
            if len(common):
                pred = klt.predict_rotated(self.cameras[i].camera, uv0[i0], self._R_C1C0(i, self._R_S_kf_cur))
                parallax.append(np.linalg.norm(st.uv[i1] - pred, axis=1))
        if parallax and np.median(np.concatenate(parallax)) > cfg.kf_min_parallax_px:
            counts["kf_parallax"] += 1
            return True
        return False

    def _start_keyframe(self, stamp_ns: int, images: list[np.ndarray], counts) -> None:
        """Refine the keyframe's tracks (affine KLT), keep its observations and describe them (ORB)."""
        if self.cfg.klt_affine and self.cfg.affine_keyframes_only:
            for st, image in zip(self._cams, images):
                if len(st.ids):
                    st.uv = self._refine_affine(st, image, st.uv, counts)
        self._kf_id += 1
        self._kf_stamp = int(stamp_ns)
        self._kf_obs = [(st.ids.copy(), st.uv.copy()) for st in self._cams]
        self._R_S_kf_cur = np.eye(3)
        tracks = [(st.ids, st.uv) for st in self._cams]
        if self._orb is not None and (kd := describe_keyframe(self._orb, self._kf_id, stamp_ns, tracks, images)):
            self.keyframe_descriptors.append(kd)
