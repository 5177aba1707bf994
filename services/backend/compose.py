"""The back end's composition root: the one place that builds what the back end is made of from the system config
and hands each part its collaborators in its constructor (the seams are the protocols of
services/backend/window/protocols.py).

Who needs whom: the estimator takes the occupancy terms (extra factors) and the loop closer's keyframe history
(marginalisation listener); the history feeds the loop closer, which needs only the cameras; the occupancy terms take
the loop closure's :class:`PublishedFrame` as their submap anchoring, and that reads the estimator's window when a
submap is anchored. The one cycle (estimator -> terms -> anchoring -> estimator) is cut at its last link, which is
only used while frames and map inputs flow, never during construction: the anchoring gets a late-bound provider of
the estimator, bound as soon as the estimator is built. So the order is: cameras; loop closer, history and published
frame; occupancy terms; estimator (provider bound); the window and loop-closure stages.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from pathlib import Path

from services.backend.loop.history import KeyframeHistory
from services.backend.loop.loop_closer import LoopCloser
from services.backend.loop.loop_thread import ThreadedLoopCloser
from services.backend.loop.published_frame import PublishedFrame
from services.backend.loop.saved_map import SparseMapError, load_sparse
from services.backend.loop.stage import LoopClosure
from services.backend.o2p.terms import OccupancyTerms
from services.backend.window.estimator import WindowedVioEstimator
from services.backend.window.stage import WindowStage
from shared.config import ConfigError
from shared.map_folder import SPARSE_FILE, run_map_dir, sparse_path
from shared.vio.cameras import rig_cameras

log = logging.getLogger("sigmaslam.backend")


@dataclasses.dataclass(frozen=True)
class BackendParts:
    """The back end's stages: the keyframe window, and when configured the occupancy-to-point terms
    (``o2p.enabled``) and loop closure (``loop.enabled``)."""

    window: WindowStage
    o2p: OccupancyTerms | None
    loop_closure: LoopClosure | None


def saved_map_to_load(lc, restarted: bool) -> Path | None:
    """The sparse map a back end starts from: after a restart, its run's own last checkpoint
    (``loop.map_output``/map/sparse.npz, which holds the saved map it localised in, if any); else
    ``loop.prior_map``; None for neither. A configured ``prior_map`` that is not there is an error (ConfigError:
    the process stops with the message); a missing checkpoint only means starting afresh (logged)."""
    if restarted and lc.map_output:
        ckpt = run_map_dir(lc.map_output) / SPARSE_FILE
        if ckpt.is_file():
            log.warning("back end restarted: relocalising in this run's last saved map %s", ckpt)
            return ckpt
        log.warning("back end restarted without a saved map (%s): starting a new world frame", ckpt)
    if not lc.prior_map:
        return None
    path = sparse_path(lc.prior_map)
    if not path.is_file():
        raise ConfigError(f"loop.prior_map: {path} not found (a run's folder with map/sparse.npz, or the map/ "
                          "folder itself)")
    return path


def _loop_closer(lc, cams, restarted: bool) -> LoopCloser:
    """The loop closer, localising in the saved map :func:`saved_map_to_load` names (if any)."""
    closer = LoopCloser(lc, cams)
    prior = saved_map_to_load(lc, restarted)
    if prior is not None:
        try:
            closer.load_prior(load_sparse(prior))
        except SparseMapError as exc:
            if not restarted:
                raise ConfigError(f"loop.prior_map: {exc}") from exc
            log.warning("saved map not usable (%s): starting a new world frame", exc)
        else:
            log.info("localising in the saved map %s (%d keyframes)", prior, len(closer.prior))
    return closer


class _LateBound:
    """A value handed to constructors before it exists, bound once right after (the root's one cycle)."""

    def __init__(self, what: str) -> None:
        self.what, self.value = what, None

    def bind(self, value):
        self.value = value
        return value

    def __call__(self):
        if self.value is None:
            raise RuntimeError(f"{self.what} read before it was built")
        return self.value


def build_backend(cfg, cameras, restarted: bool = False) -> BackendParts:
    """The back end's parts from the system config ``cfg`` and the rig ``cameras`` (``shared.rig`` calibrations);
    ``restarted``: after a supervisor restart (the first state says 'reset'; the loop closer relocalises in the run's
    last saved map)."""
    bc, lc = cfg.backend, cfg.loop
    cams = rig_cameras(cameras)
    window = _LateBound("the back end's estimator")
    history = runner = published = None
    if lc.enabled:
        runner = ThreadedLoopCloser(_loop_closer(lc, cams, restarted), lc.synchronous)
        history = KeyframeHistory(listeners=[runner.submit_record])
        published = PublishedFrame(history, window, lc.correct_state, cfg.o2p.anchor_tolerance_ms)
    # no dense factors until the window has a metric scale (one camera: OccupancyTerms.window_factors)
    o2p = OccupancyTerms(cfg.o2p, anchoring=published) if cfg.o2p.enabled else None
    est = window.bind(WindowedVioEstimator(bc, cams, extra_factors=[o2p] if o2p is not None else [],
                                           on_marginalise=[history] if history is not None else []))
    loop_closure = None
    if lc.enabled:
        session = {"source": str(cfg.rig.calibration), "restarted": bool(restarted),
                   "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
        loop_closure = LoopClosure(lc, est, history, runner, published, session)
    return BackendParts(WindowStage(est, restarted), o2p, loop_closure)
