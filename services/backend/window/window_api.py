"""The estimator's read API (:class:`WindowReadApi`, a base of :class:`services.backend.window.estimator.WindowedVioEstimator`):
what the fast path, initialisation, loop closure and the node read from the window, kept apart from the solve.
Every call answers at the current estimate and returns copies or new containers (the observation arrays of
:meth:`WindowReadApi.observations_of` excepted, which are the window's own)."""

from __future__ import annotations

import dataclasses

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L

from shared.vio.cameras import VioCamera
from services.backend.window.gravity_align import GravityAlignment
from services.backend.window.landmarks import WindowLandmarks, gather_landmarks


class WindowReadApi:
    """Read-only views of the window; the attributes it reads are the estimator's (set in its constructor)."""

    def window_landmarks(self, max_count: int | None = None) -> WindowLandmarks:
        """The window's well-constrained landmarks at the current estimate, at most ``max_count`` (default
        ``cfg.max_published_landmarks``): those last seen most recently, then seen most often, are kept."""
        limit = self.cfg.max_published_landmarks if max_count is None else max_count
        return gather_landmarks(self._book.by_landmark, self._book.in_graph, self.values, self.stamps, limit)

    # ---------------------------------------------------------------- introspection
    def window_counts(self) -> dict[str, int]:
        """Sizes that bound the per-frame cost: states in the window, landmarks with factors, total variables."""
        return {"keyframes": len(self.keyframes), "states": len(self.stamps), "landmarks": len(self._book.in_graph),
                "variables": int(self.values.size()), "observed_landmarks": len(self._book.by_landmark)}

    # ---------------------------------------------------------------- read API (mono_init, loop/history.py)
    @property
    def focal_px(self) -> np.ndarray:
        """(C,) focal length of each camera [px] (a copy)."""
        return self._focal.copy()

    @property
    def T_SC(self) -> np.ndarray:
        """(C,4,4) pose of each camera in the body frame S (a copy)."""
        return self._T_SC.copy()

    def cameras_in_use(self) -> list[VioCamera]:
        """The rig's cameras with the extrinsics the window uses now (the refined ones with refinement on)."""
        return [dataclasses.replace(c, T_SC=T.copy()) for c, T in zip(self.cameras, self._T_SC)]

    @property
    def extrinsic_covariance(self) -> np.ndarray:
        """(C,6,6) covariance of each camera's carried T_SC prior (rotation [rad], translation [m]), refinement on."""
        return self._extrinsics.covariance.copy()

    @property
    def prior_covariance(self) -> np.ndarray:
        """(15,15) covariance of the prior on the window's oldest state, order (rotation, position, velocity,
        accelerometer bias, gyro bias) (a copy)."""
        return self._prior.cov.copy()

    @property
    def prior_carried(self) -> int:
        """Marginalisations that kept the previous prior's covariance (the window had no marginals)."""
        return self._prior.carried

    @property
    def gravity_alignment(self) -> GravityAlignment | None:
        """What the moving start's gravity alignment did (None: not done, gravity_align.py)."""
        return self._gravity.result

    @property
    def gravity_alignment_failures(self) -> int:
        """Gravity alignments of a moving start refused so far."""
        return self._gravity.failures

    @property
    def mono_pending(self) -> bool:
        """One camera: the window has no metric scale yet (it neither stood still nor was rebuilt by mono_init)."""
        return self._mono_pending

    def observations_of(self, state: int) -> dict[int, tuple[tuple[int, np.ndarray], ...]]:
        """landmark -> ((camera, normalised xy (2,)), ...) of the window's observations at ``state``, in the
        order landmarks were first seen; a new dict (the xy arrays are the window's own: do not modify them)."""
        return self._book.of_state(state)

    def window_points(self) -> tuple[np.ndarray, np.ndarray]:
        """(ids (N,), p_W (N,3)) of every triangulated landmark with factors in the window, at the current estimate."""
        ids = np.array(sorted(self._book.in_graph), np.int64)
        p = np.array([self.values.atPoint3(L(int(lm))) for lm in ids], float).reshape(-1, 3)
        return ids, p

    def landmark_in_graph(self, lm: int) -> bool:
        """Whether landmark ``lm`` is triangulated and has factors in the window's graph (a value L(lm))."""
        return lm in self._book.in_graph

    def imu_factor_to(self, state: int) -> gtsam.NonlinearFactor | None:
        """The IMU factor from the keyframe before ``state`` to ``state`` (None for the oldest state)."""
        return self._imu_factors.get(state)

    def joint_marginal(self, keys: list[int]) -> np.ndarray | None:
        """Joint marginal covariance of gtsam ``keys`` from the last optimisation's marginals (computed at keyframes
        or with ``compute_covariance``); None when there are none or gtsam cannot compute it."""
        if self._marginals is None:
            return None
        try:
            return self._marginals.jointMarginalCovariance(keys).fullMatrix()
        except RuntimeError:
            return None
