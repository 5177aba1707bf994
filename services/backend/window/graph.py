"""How the keyframe window's graph is built and kept (:class:`WindowGraph`, a base of
:class:`services.backend.window.estimator.WindowedVioEstimator`): a new state predicted by the IMU, its observations and
stand-still factors, triangulated landmarks, the graph of every cached factor, outlier rejection, removing a state
and marginalising the oldest keyframe. The attributes it reads are the estimator's (set in its constructor)."""

from __future__ import annotations

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, L, V, X

from services.backend.window.still import mono_frame_factors
from services.backend.window.triangulation import new_landmarks
from shared.vio.imu_factors import imu_factor, predict
from shared.vio.window_rules import reprojection_outliers, state_keys


class WindowGraph:
    """The window's states, observations, landmarks and factors."""

    def _add_state(self, stamp_ns: int) -> int:
        k = self.keyframes[-1]
        bias = self.values.atConstantBias(B(k))
        pim = self.imu.preintegrate(self.params, bias, self.stamps[k], stamp_ns)
        n = self._new_state(stamp_ns)
        T, v = predict(pim, self.values.atPose3(X(k)).matrix(), self.values.atVector(V(k)), bias)
        self.values.insert(X(n), gtsam.Pose3(T))
        self.values.insert(V(n), v)
        self.values.insert(B(n), bias)
        self._imu_factors[n] = imu_factor(pim, (X(k), V(k), B(k)), (X(n), V(n), B(n)))
        return n

    def _add_observations(self, n: int, ids, cams, uv) -> None:
        for c in np.unique(cams):  # camera by camera, as the factors' observation indices j count them
            for lm, p in zip(ids[cams == c], self._vision.undistort(cams[cams == c], uv[cams == c])):
                self._book.add(n, int(lm), int(c), p)

    def _add_still(self, n: int, k: int) -> None:
        """Relative-pose and zero-velocity factors keyframe k -> state n when the (first camera's) image stands still:
        one camera, or a rig of several with ``backend.still_stereo`` until it first moves."""
        if n == k or self._still_over:
            return
        factors, still = mono_frame_factors(self._book.by_landmark, k, n, float(self._focal[0]), self._T_SC[0][:3, :3], self.cfg,
                                            self._mono_pending)
        # several cameras: only at the start (mid-run pauses have held marginals; these made 5-7 marginalisations fail)
        self._still_over = len(self.cameras) > 1 and not still
        if factors:
            self._still[n] = factors
        self.still_frames += still

    def _triangulate_new(self, n: int) -> None:
        for lm, p in new_landmarks(self._book.by_landmark, self._book.in_graph, n, lambda s: self.values.atPose3(X(s)).matrix(),
                                   self._T_SC, self._focal, self.cfg):
            if self.values.exists(L(lm)):
                self.values.update(L(lm), p)
            else:
                self.values.insert(L(lm), p)
            self._book.in_graph.add(lm)

    def _projection(self, lm: int, n: int, j: int, c: int, xy: np.ndarray) -> gtsam.NonlinearFactor:
        if self._extrinsics is None:
            return self._book.factor(lm, n, j, lambda: self._vision.factor(xy, c, X(n), L(lm)))
        return self._book.factor(lm, n, j, lambda: self._vision.factor_with_extrinsic(
            xy, c, X(n), self._extrinsics.keys[c], L(lm)))

    def _build_graph(self, n: int) -> gtsam.NonlinearFactorGraph:
        g = gtsam.NonlinearFactorGraph()
        for f in self._prior.factors:
            g.add(f)
        for f in () if self._extrinsics is None else self._extrinsics.priors:
            g.add(f)
        for k in self.keyframes[1:]:
            g.add(self._imu_factors[k])
        if n != self.keyframes[-1]:
            g.add(self._imu_factors[n])
        for k in self._still:
            for f in self._still[k]:
                g.add(f)
        for lm in self._book.in_graph:
            for s, obs in self._book.by_landmark[lm].items():
                for j, (c, xy) in enumerate(obs):
                    g.add(self._projection(lm, s, j, c, xy))
        for source in self._extra_factors:
            for f in source.window_factors(self):
                g.add(f)
        return g

    def _reject_outliers(self) -> bool:
        """Remove observations whose reprojection error exceeds the bound; drop landmarks left with < 2.

        Returns True when anything was removed."""
        book = self._book
        if not book.in_graph:
            return False
        touched = reprojection_outliers(self.values, book.by_landmark, book.in_graph, self.stamps, self._T_SC,
                                        self._focal, self.cfg.min_depth_m, self.cfg.max_reproj_error_px)
        for (lm, s), drop in touched.items():
            book.set(lm, s, [o for j, o in enumerate(book.by_landmark[lm][s]) if j not in drop])
        for lm in {lm for lm, _ in touched}:
            if book.count(lm) < 2:
                self._drop_landmark(lm)
        return bool(touched)

    def _drop_landmark(self, lm: int) -> None:
        self._book.in_graph.discard(lm)
        if self.values.exists(L(lm)):
            self.values.erase(L(lm))
        self._book.forget_if_unobserved(lm)

    def _remove_state(self, n: int) -> None:
        for lm in self._book.remove_state(n):
            self._drop_landmark(lm)
        self._imu_factors.pop(n, None)
        self._still.pop(n, None)
        for key in state_keys(n):
            self.values.erase(key)
        del self.stamps[n]

    def _marginalise_oldest(self) -> None:
        old, new = self.keyframes[0], self.keyframes[1]
        for listener in self._on_marginalise:
            listener.on_marginalise(self, old, new)
        self._prior.carry(self.values, new, self.joint_marginal, self._extrinsics, self._T_SC)
        self.keyframes.pop(0)
        self._imu_factors.pop(new, None)
        self._still.pop(new, None)  # refers to the old state; the marginal prior holds its information
        self._remove_state(old)

    def forget_triangulations(self) -> None:
        """Every landmark leaves the graph (its observations stay; it is triangulated again from the poses)."""
        for lm in self._book.in_graph:
            self.values.erase(L(lm))
        self._book.in_graph.clear()
