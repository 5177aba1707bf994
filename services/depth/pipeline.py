"""The depth algorithm without transport: rectify a stereo frame, run stereo (network or SGBM), run MVS
on posed keyframes when available, fuse (eq. 14).

::

    pipe = DepthPipeline(cfg, cam_left, cam_right)
    pipe.remember_frame(stamp_ns, raw_left)              # every frame (cheap), for keyframes announced later
    pipe.update_keyframes(stamps_ns, T_WS)               # after each optimisation
    pipe.update_landmarks(p_W, last_seen_ns, num_obs)    # estimator/landmarks: the MVS prior
    out = pipe.process(stamp_ns, raw_left, raw_right, T_WS)   # T_WS None when unknown
    out.stereo, out.mvs, out.fused                       # (depth, sigma) float32 (H,W) [m], NaN invalid

All depth maps live in the rectified left camera N0: intrinsics ``pipe.K``, pose in the body ``pipe.T_SC``.
Pixels outside ``pipe.valid`` (not covered by the raw left and right images, plus ``depth.border_margin_px``;
services/depth/coverage.py) are NaN in every output: the networks make up depth there.

With ``depth.mono`` (``DepthPipeline(cfg, cam_left)``, ``process(stamp_ns, raw_left, None, T_WS)``) there is no
right camera and no stereo network: N0 is the left camera undistorted to the same pinhole K (axes of the
camera itself), the result's ``stereo`` is None and ``fused`` is the MVS depth, or None while MVS has no
source views.
"""
from __future__ import annotations

import logging
from collections import OrderedDict
from dataclasses import dataclass

import cv2
import numpy as np

from services.depth.config import DepthConfig
from services.depth.coverage import covered, stereo_valid, valid_region
from services.depth.flying import flying_pixels
from services.depth.prior import landmark_prior
from services.depth.sgbm import SgbmParams, sgbm_depth, stereo_heuristic_sigma
from services.depth.uncertainty import disparity_to_depth, fuse, logdepth_to_depth
from services.depth.views import select_sources
from shared.camera import CameraCalib, rectified_intrinsics, stereo_rectification
from shared.occupancy.uncertain_pixels import carve_only_pixels

log = logging.getLogger(__name__)


FLYING_MONO_BASELINE_M = 0.1  # depth.mono: the baseline that turns inverse depth into disparity for the flying pixels


@dataclass
class DepthResult:
    stereo: tuple[np.ndarray, np.ndarray] | None  # None with depth.mono
    mvs: tuple[np.ndarray, np.ndarray] | None
    fused: tuple[np.ndarray, np.ndarray] | None  # None only with depth.mono while MVS has no source views
    T_WC: np.ndarray | None
    method: str
    n_sources: int
    n_prior: int = 0  # landmark pixels in the MVS prior
    surface_max_relative_sigma: float = 0.0  # pixels with sigma > this x depth place no surface (0: all do)


@dataclass
class _View:
    image: np.ndarray  # rectified left image (H,W) uint8
    T_WC: np.ndarray | None
    features: object = None  # cached MVS encoder features (torch tensor)


class DepthPipeline:
    def __init__(self, cfg: DepthConfig, cam_left: CameraCalib, cam_right: CameraCalib | None = None) -> None:
        self.cfg = cfg
        size = (cfg.width, cfg.height)
        if cfg.mono:  # the left camera alone, undistorted to the rectified K (no right camera to align axes to)
            self.rect = None
            self.raw_shapes = ((cam_left.camera.height, cam_left.camera.width), None)
            self.K = rectified_intrinsics(cam_left, size, cfg.fov_scale)
            self.T_SC = np.asarray(cam_left.T_SC, np.float64).copy()
            self._left_maps = cam_left.camera.remap_to_pinhole(self.K, size)
            self.baseline_m = 0.0
            self.valid = valid_region([covered(self._left_maps, self.raw_shapes[0])], cfg.border_margin_px)
        else:
            if cam_right is None:
                raise ValueError("stereo depth needs a right camera (or depth.mono)")
            self.rect = stereo_rectification(cam_left, cam_right, size, cfg.fov_scale)
            self.raw_shapes = ((cam_left.camera.height, cam_left.camera.width), (cam_right.camera.height, cam_right.camera.width))
            self.K = self.rect.K
            self.T_SC = self.rect.T_SN0
            self._left_maps = self.rect.maps0
            self.baseline_m = self.rect.baseline_m
            self.valid = stereo_valid(self.rect, self.raw_shapes, cfg.border_margin_px)
        # self.valid: pixels whose depth is kept (covered by the raw image(s), away from uncovered ones)
        self.f_px = float(self.K[0, 0])
        self.sgbm_params = SgbmParams(num_disparities=cfg.sgbm_num_disparities, block_size=cfg.sgbm_block_size)
        self.method = cfg.method
        self.stereo_net = self.mvs_net = None
        self.stereo_gain = self.mvs_gain = 1.0
        self._recent: OrderedDict[int, np.ndarray] = OrderedDict()
        self._views: OrderedDict[int, _View] = OrderedDict()
        self._landmarks: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # p_W, last_seen_ns, num_obs
        self.prior_rejected = 0  # landmarks not in the prior (outside the view or depth range, or over the cap)
        self.confident_px = self.uncertain_px = 0  # pixels of the fused (published) maps kept / dropped as uncertain
        self.flying_px = 0  # stereo pixels dropped as flying (services/depth/flying.py)
        if self.method == "network":
            self._load_networks()
        # a learned sigma says which pixels are unsure (depth.max_relative_sigma); SGBM's or the heuristic one only
        # grows with depth
        self.learned_sigma = self.method == "network" and (cfg.mono or cfg.stereo_sigma == "network")

    # ------------------------------------------------------------------ setup
    def _load_networks(self) -> None:
        import torch

        from services.depth import weights

        device = self.cfg.device
        self.device = ("cuda" if torch.cuda.is_available() else "cpu") if device == "auto" else device
        torch.set_num_threads(max(1, self.cfg.threads))
        self.stereo_precision = weights.resolve_precision(self.cfg.stereo_precision, self.device)
        if self.cfg.mono:  # MVS alone: without its weights there is no depth at all
            self.mvs_net, meta = weights.load(weights.weights_path(self.cfg.mvs_weights, "mvs.pt"), self.device)
            self.mvs_gain = float(meta["gain"])
            return
        stereo_path = weights.weights_path(self.cfg.stereo_weights, weights.DEFAULT_STEREO)
        try:
            self.stereo_net, meta = weights.load(stereo_path, self.device)
            self.stereo_gain = float(meta["gain"])
            log.info("depth: stereo network %s on %s in %s (depth.stereo_precision %s), %d torch threads",
                     stereo_path.name, self.device, self.stereo_precision, self.cfg.stereo_precision,
                     torch.get_num_threads())
        except weights.WeightsError as exc:
            log.warning("depth: %s; falling back to SGBM with heuristic sigma", exc)
            self.method = "sgbm"
            return
        if self.cfg.use_mvs:
            try:
                self.mvs_net, meta = weights.load(weights.weights_path(self.cfg.mvs_weights, "mvs.pt"), self.device)
                self.mvs_gain = float(meta["gain"])
            except weights.WeightsError as exc:
                log.warning("depth: %s; running stereo only", exc)

    def _inference(self, precision: str = "float32"):
        """Context of every network call (services.depth.weights.inference)."""
        from services.depth import weights

        return weights.inference(self.device, precision)

    # ------------------------------------------------------------------ keyframes
    def remember_frame(self, stamp_ns: int, raw_left: np.ndarray) -> None:
        """Keep a recent raw left image so that a keyframe announced later finds its image."""
        if self.mvs_net is None:
            return
        self._recent[int(stamp_ns)] = raw_left
        while len(self._recent) > self.cfg.frame_history:
            self._recent.popitem(last=False)

    def update_keyframes(self, stamps_ns: np.ndarray, T_WS: np.ndarray) -> None:
        """New poses of keyframes; those with a remembered image become MVS source candidates."""
        if self.mvs_net is None:
            return
        for t, T in zip(np.asarray(stamps_ns, np.int64).tolist(), np.asarray(T_WS).reshape(-1, 4, 4)):
            T_WC = T @ self.T_SC
            if t in self._views:
                self._views[t].T_WC = T_WC
            elif t in self._recent:
                left = cv2.remap(self._recent[t], *self._left_maps, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
                self._views[t] = _View(left, T_WC)
        while len(self._views) > self.cfg.keyframe_views:
            self._views.popitem(last=False)

    @property
    def n_keyframe_views(self) -> int:
        return len(self._views)

    def update_landmarks(self, p_W: np.ndarray, last_seen_ns: np.ndarray, num_observations: np.ndarray) -> None:
        """The estimator's latest landmarks (replacing the previous ones): the MVS network's sparse prior."""
        p_W = np.asarray(p_W, np.float64).reshape(-1, 3)
        last, nobs = np.asarray(last_seen_ns, np.int64).reshape(-1), np.asarray(num_observations).reshape(-1)
        if len(last) != len(p_W) or len(nobs) != len(p_W):
            raise ValueError(f"landmarks: {len(p_W)} positions, {len(last)} stamps, {len(nobs)} counts")
        self._landmarks = (p_W, last, nobs)

    def mvs_prior(self, stamp_ns: int, T_WC: np.ndarray) -> np.ndarray | None:
        """Sparse prior depth (H,W) [m] (0: none) of the frame at ``stamp_ns``, pose T_WC: the landmarks seen
        within ``depth.prior_max_age_s`` of it, projected (services/depth/prior.py); None without landmarks."""
        if self._landmarks is None or self.mvs_net is None or self.cfg.prior_max_points <= 0:
            return None
        p_W, last, nobs = self._landmarks
        recent = np.abs(last - int(stamp_ns)) <= self.cfg.prior_max_age_s * 1e9
        pr = landmark_prior(p_W[recent], T_WC, self.K, (self.cfg.height, self.cfg.width), self.mvs_net.min_depth,
                            self.mvs_net.max_depth, self.cfg.prior_max_points, nobs[recent])
        self.prior_rejected += pr.rejected + int((~recent).sum())
        return pr.depth

    # ------------------------------------------------------------------ per frame
    def stereo(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Depth and sigma [m] of a rectified pair, by the configured method."""
        if self.method == "sgbm":
            return sgbm_depth(left, right, self.f_px, self.baseline_m, self.cfg.heuristic_sigma_model,
                              self.cfg.heuristic_sigma_coeff, self.sgbm_params)
        import torch

        with self._inference(self.stereo_precision):
            t = lambda a: torch.from_numpy(a).float()[None, None].to(self.device)
            u, su = (x.float() for x in self.stereo_net(t(left), t(right)))
        depth, sigma = disparity_to_depth(u[0].cpu().numpy(), su[0].cpu().numpy() * self.stereo_gain, self.f_px,
                                          self.baseline_m)
        if self.cfg.stereo_sigma == "heuristic":  # the network's depth with SGBM's sigma model (depth.stereo_sigma)
            sigma = stereo_heuristic_sigma(depth, self.f_px, self.baseline_m, self.cfg.heuristic_sigma_model,
                                           self.cfg.heuristic_sigma_coeff)
        return depth, sigma

    def warm_up(self) -> None:
        """One inference on a blank image, so that the first real frame does not also pay for the networks' lazy
        set-up (allocations, kernel selection: 1-3 s on a CPU) while the stream has already started."""
        blank = np.zeros((self.cfg.height, self.cfg.width), np.uint8)
        if self.stereo_net is not None and not self.cfg.mono:
            self.stereo(blank, blank)
        if self.mvs_net is not None:
            import torch

            with self._inference():
                self.mvs_net.encoder(torch.from_numpy(blank).float()[None, None].to(self.device))

    def _mask(self, ds: tuple[np.ndarray, np.ndarray], count: bool = False
              ) -> tuple[tuple[np.ndarray, np.ndarray], np.ndarray]:
        """Depth and sigma with NaN outside ``self.valid`` and on flying pixels (services/depth/flying.py; ``count``
        adds them to ``self.flying_px``), and the flying pixels' mask."""
        d, s = (np.where(self.valid, a, np.float32(np.nan)).astype(np.float32, copy=False) for a in ds)
        cfg = self.cfg
        fly = flying_pixels(d, self.f_px * (self.baseline_m or FLYING_MONO_BASELINE_M), cfg.flying_radius_px,
                            cfg.flying_rel_jump, cfg.flying_min_gradient, cfg.flying_margin)
        if count:
            self.flying_px += int(np.count_nonzero(fly))
        return _nan_where((d, s), fly), fly

    @property
    def surface_max_relative_sigma(self) -> float:
        """``depth.max_relative_sigma`` where the sigma is learned, else 0 (SGBM's and the heuristic sigma grow with
        depth alone: the rule would cut far depth)."""
        return self.cfg.max_relative_sigma if self.learned_sigma else 0.0

    def _count_uncertain(self, ds: tuple[np.ndarray, np.ndarray] | None) -> None:
        """Add the published map's pixels that place a surface and those too uncertain to (sigma >
        ``depth.max_relative_sigma`` x depth: they only free space, shared/occupancy/uncertain_pixels.py) to
        ``self.confident_px`` / ``self.uncertain_px``."""
        if ds is None:
            return
        carve = carve_only_pixels(*ds, self.surface_max_relative_sigma)
        if carve is None:
            return
        n_bad = int(np.count_nonzero(carve))
        self.uncertain_px += n_bad
        self.confident_px += int(np.count_nonzero(np.isfinite(ds[0]))) - n_bad

    def _features(self, view: _View):
        if view.features is None:
            import torch

            with self._inference():
                view.features = self.mvs_net.encoder(torch.from_numpy(view.image).float()[None, None].to(self.device))
        return view.features

    def mvs(self, left: np.ndarray, T_WC: np.ndarray, prior_depth: np.ndarray | None = None
            ) -> tuple[tuple[np.ndarray, np.ndarray] | None, int]:
        """MVS depth and sigma [m] of the rectified left image at pose T_WC from the keyframe views
        (None when no source view qualifies), and the number of source views used."""
        views = [v for v in self._views.values() if v.T_WC is not None]
        if self.mvs_net is None or not views:
            return None, 0
        idx = select_sources(T_WC, np.stack([v.T_WC for v in views]), self.cfg.mvs_sources,
                             self.cfg.mvs_min_baseline_m, self.cfg.mvs_max_baseline_m, self.cfg.mvs_max_angle_deg)
        if len(idx) == 0:
            return None, 0
        import torch

        with self._inference():
            f_ref, ctx = self.mvs_net.encoder(torch.from_numpy(left).float()[None, None].to(self.device))
            f_src = torch.stack([self._features(views[i])[0][0] for i in idx])[None]
            T_src_ref = torch.from_numpy(np.stack([np.linalg.inv(views[i].T_WC) @ T_WC for i in idx])).float()[None]
            K = torch.from_numpy(self.K).float()[None]
            prior = None if prior_depth is None else torch.from_numpy(prior_depth).float()[None]
            ld, sl = self.mvs_net.forward_features(f_ref, ctx, f_src.to(self.device), K.to(self.device),
                                                   T_src_ref.to(self.device), prior, left.shape)
        d, s = logdepth_to_depth(ld[0].cpu().numpy(), sl[0].cpu().numpy() * self.mvs_gain)
        return self._mask((d, s), count=self.cfg.mono)[0], len(idx)

    def process(self, stamp_ns: int, raw_left: np.ndarray, raw_right: np.ndarray | None,
                T_WS: np.ndarray | None = None) -> DepthResult:
        if self.cfg.mono:
            return self._process_mono(stamp_ns, raw_left, T_WS)
        if raw_left.shape != self.raw_shapes[0] or raw_right.shape != self.raw_shapes[1]:
            raise ValueError(f"images of shape {raw_left.shape}/{raw_right.shape}, calibration says {self.raw_shapes}")
        left, right = self.rect.rectify(raw_left, raw_right)
        stereo, fly = self._mask(self.stereo(left, right), count=True)
        T_WC, mvs, n_src, n_prior = self._posed_mvs(stamp_ns, left, T_WS)
        if mvs is not None:  # a silhouette the stereo pair sees is one: MVS alone there would bring the curtain back
            mvs = _nan_where(mvs, fly)
        fused = stereo if mvs is None else fuse(*stereo, *mvs, self.cfg.fusion_correlation)
        self._count_uncertain(fused)
        return DepthResult(stereo, mvs, fused, T_WC, self.method, n_src, n_prior, self.surface_max_relative_sigma)

    def _process_mono(self, stamp_ns: int, raw_left: np.ndarray, T_WS: np.ndarray | None) -> DepthResult:
        """depth.mono: MVS depth of the undistorted left image, None before a pose and source views exist."""
        if raw_left.shape != self.raw_shapes[0]:
            raise ValueError(f"image of shape {raw_left.shape}, calibration says {self.raw_shapes[0]}")
        left = cv2.remap(raw_left, *self._left_maps, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        T_WC, mvs, n_src, n_prior = self._posed_mvs(stamp_ns, left, T_WS)
        self._count_uncertain(mvs)
        return DepthResult(None, mvs, mvs, T_WC, "mvs", n_src, n_prior, self.surface_max_relative_sigma)

    def _posed_mvs(self, stamp_ns: int, left: np.ndarray, T_WS: np.ndarray | None):
        """(T_WC, MVS depth and sigma or None, source views, prior pixels) of the rectified left image; no MVS
        without a pose."""
        if T_WS is None:
            return None, None, 0, 0
        T_WC = np.asarray(T_WS) @ self.T_SC
        prior = self.mvs_prior(stamp_ns, T_WC)
        mvs, n_src = self.mvs(left, T_WC, prior)
        n_prior = 0 if prior is None or mvs is None else int(np.count_nonzero(prior))
        return T_WC, mvs, n_src, n_prior


def _nan_where(ds: tuple[np.ndarray, np.ndarray], mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Depth and sigma with NaN where ``mask``."""
    return tuple(np.where(mask, np.float32(np.nan), a) for a in ds)


def pipeline_for_rig(cfg: DepthConfig, cameras) -> DepthPipeline:
    """The depth pipeline of a rig (shared.rig calibrations): the left camera alone with ``cfg.mono``, else the
    stereo pair; ValueError naming the rig's cameras when one of them is not in it."""
    by_name = {c.name: c for c in cameras}
    missing = [n for n in (cfg.left_camera, *(() if cfg.mono else (cfg.right_camera,))) if n not in by_name]
    if missing:
        raise ValueError(f"depth cameras {missing} not in the rig ({sorted(by_name)}; depth.mono=true for a "
                         f"one-camera rig)")
    return DepthPipeline(cfg, by_name[cfg.left_camera], None if cfg.mono else by_name[cfg.right_camera])
