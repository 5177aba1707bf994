"""Pose graph of keyframes that left the optimisation window (paper eq. 5, relative-pose term).

Nodes are keyframe body poses ``T_WS``; consecutive nodes are linked by the relative pose the window
estimated, with the covariance of that relative pose taken from the window's joint marginal covariance
(:func:`relative_covariance`); each node also keeps the window's tilt (roll and pitch: gravity is observable
in visual-inertial odometry, only yaw and position drift) through an attitude factor of ``attitude_sigma_rad``,
so that a loop or map-to-map term cannot tilt the trajectory (a tilt of a few tenths of a degree moves poses
metres away by cm); accepted loops add relative-pose factors from PnP (robust, Cauchy); map-to-map
occupancy-to-point terms (eq. 5-7, services/backend/o2p/terms.py) tie the keyframes anchoring two submaps. The graph
is solved by Levenberg-Marquardt (in the loop closer's own thread, see services/backend/loop/loop_closer.py, so the
estimator never waits for it).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import gtsam
import numpy as np

from shared.geometry import inv_T


_UP = np.array([0.0, 0.0, 1.0])  # W's z axis, opposite to gravity (shared/vio/imu_factors.py)


def _sym(key: int) -> int:
    return gtsam.symbol("k", int(key))


def relative_covariance(T_WA: np.ndarray, T_WB: np.ndarray, joint: np.ndarray) -> np.ndarray:
    """Covariance (6,6) of T_AB = T_WA^-1 T_WB from the joint (12,12) marginal covariance of the two Pose3s
    (gtsam tangent order [rot, trans] each, A first)."""
    T_AB = inv_T(T_WA) @ T_WB
    H1 = -gtsam.Pose3(inv_T(T_AB)).AdjointMap()
    H = np.hstack([H1, np.eye(6)])
    C = H @ joint @ H.T
    return 0.5 * (C + C.T)


def _noise(cov: np.ndarray, robust_k: float | None = None):
    model = gtsam.noiseModel.Gaussian.Covariance(np.asarray(cov, float))
    if robust_k is None:
        return model
    return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(robust_k), model)


@dataclass(frozen=True)
class LoopConstraint:
    old_key: int
    new_key: int
    T_old_new: np.ndarray  # relative body pose
    covariance: np.ndarray  # (6,6), gtsam Pose3 tangent order


class PoseGraph:
    """Keyframe nodes (added in time order), odometry and loop factors; not thread safe by itself."""

    def __init__(self, prior_sigma_rad: float = 1e-4, prior_sigma_m: float = 1e-4, loop_cauchy_k: float = 3.0,
                 attitude_sigma_rad: float = 0.0):
        self.graph = gtsam.NonlinearFactorGraph()
        self.initial = gtsam.Values()
        self.odom: dict[int, np.ndarray] = {}  # key -> odometry (window) estimate T_WS
        self.keys: list[int] = []
        self.loops: list[LoopConstraint] = []
        self.map_to_map: list = []  # services.backend.o2p.terms.MapToMap terms in the graph
        self.last_map_to_map_reason = ""  # why the last term offered was rejected ('' accepted)
        self._prior = (prior_sigma_rad, prior_sigma_m)
        self._cauchy = loop_cauchy_k
        self._attitude = (gtsam.noiseModel.Isotropic.Sigma(2, attitude_sigma_rad) if attitude_sigma_rad > 0 else None)
        self.estimate: dict[int, np.ndarray] = {}
        self.fixed: set[int] = set()  # nodes of a saved map (add_fixed_node): held where the map has them
        self._gauge = None  # (factor index, key, T, sigmas) of the session's first-node prior
        self._T_session = np.eye(4)  # every align_session so far: where the first node goes when it comes later
        self.edges: list[tuple[int, int, np.ndarray, np.ndarray]] = []  # odometry edges (from, to, T_rel, cov)

    def add_fixed_node(self, key: int, T_WS: np.ndarray) -> None:
        """A node of a saved map, held at ``T_WS`` (the map's frame) by a tight prior; not part of the session's
        chain (:attr:`keys`). Once a graph has fixed nodes, the session's first node is only weakly anchored, so
        that loops to the map's nodes can move the whole session into the map's frame (:meth:`align_session`)."""
        key, T_WS = int(key), np.asarray(T_WS, float)
        if key in self.odom:
            raise ValueError(f"node {key} is already in the pose graph")
        r, t = self._prior
        self.graph.add(gtsam.PriorFactorPose3(_sym(key), gtsam.Pose3(T_WS),
                                              gtsam.noiseModel.Diagonal.Sigmas(np.array([r] * 3 + [t] * 3))))
        self.initial.insert(_sym(key), gtsam.Pose3(T_WS))
        self.odom[key] = self.estimate[key] = T_WS
        self.fixed.add(key)

    def align_session(self, T: np.ndarray) -> None:
        """Move the session by ``T`` (T_map_session): its nodes' current estimates (the starting point of the next
        solve, so that loops to fixed nodes start near their solution instead of being down-weighted by their
        robust kernel as outliers) and its first node's weak gauge prior (so that a solve before those loops join
        keeps the session where it was moved)."""
        T = np.asarray(T, float)
        self._T_session = T @ self._T_session
        for k in self.keys:
            self.estimate[k] = T @ self.estimate[k]
            self.initial.update(_sym(k), gtsam.Pose3(self.estimate[k]))
        if self._gauge is not None:
            i, key, T_prior, sigmas = self._gauge
            self._gauge = (i, key, T @ T_prior, sigmas)
            self.graph.replace(i, gtsam.PriorFactorPose3(_sym(key), gtsam.Pose3(T @ T_prior),
                                                         gtsam.noiseModel.Diagonal.Sigmas(sigmas)))

    def add_node(self, key: int, T_WS: np.ndarray, rel_cov: np.ndarray | None = None,
                 T_rel: np.ndarray | None = None) -> None:
        """Append a keyframe with its window estimate; ``rel_cov`` (6,6): covariance of the relative pose from
        the previous node (required except for the first node); ``T_rel``: that relative pose as the window
        estimated it (default: from the two nodes' window estimates)."""
        T_WS = np.asarray(T_WS, float)
        if self.keys:
            prev = self.keys[-1]
            if rel_cov is None or not np.all(np.isfinite(rel_cov)):
                raise ValueError(f"keyframe {key}: relative covariance to {prev} missing or not finite")
            T_rel = inv_T(self.odom[prev]) @ T_WS if T_rel is None else np.asarray(T_rel, float)
            self.graph.add(gtsam.BetweenFactorPose3(_sym(prev), _sym(key), gtsam.Pose3(T_rel), _noise(rel_cov)))
            self.edges.append((prev, int(key), T_rel, np.asarray(rel_cov, float)))
            guess = self.estimate.get(prev, self.odom[prev]) @ T_rel  # follows the latest correction
        else:
            # the gauge: the first node where the window has it; with a saved map's nodes in the graph only weakly
            # (metres, radians), so that loops to the map decide where the session is
            r, t = (1.0, 100.0) if self.fixed else self._prior
            sigmas = np.array([r] * 3 + [t] * 3)
            guess = self._T_session @ T_WS  # moved by an alignment made before the first node
            self._gauge = (self.graph.size(), int(key), guess, sigmas)
            self.graph.add(gtsam.PriorFactorPose3(_sym(key), gtsam.Pose3(guess), gtsam.noiseModel.Diagonal.Sigmas(sigmas)))
        self.initial.insert(_sym(key), gtsam.Pose3(guess))
        if self._attitude is not None and (self.keys or self.fixed):  # W's z is up (gravity along -z): keep the window's tilt
            self.graph.add(gtsam.AttitudeFactorPose3(_sym(key), gtsam.Unit3(_UP), self._attitude,
                                                     gtsam.Unit3(T_WS[:3, :3].T @ _UP)))
        self.odom[key] = T_WS
        self.estimate[key] = guess
        self.keys.append(int(key))

    def add_loop(self, loop: LoopConstraint) -> None:
        for k in (loop.old_key, loop.new_key):
            if k not in self.odom:
                raise KeyError(f"loop refers to keyframe {k}, not in the pose graph")
        self.graph.add(gtsam.BetweenFactorPose3(_sym(loop.old_key), _sym(loop.new_key), gtsam.Pose3(loop.T_old_new),
                                                _noise(loop.covariance, self._cauchy)))
        self.loops.append(loop)

    def add_map_to_map(self, term) -> bool:
        """A map-to-map occupancy-to-point term (``MapToMap``) between the nodes anchoring its two submaps;
        False (nothing added) when its gates reject it at the current estimate (fewer than M_min of its points
        in the target's field, or chi-square); :attr:`last_map_to_map_reason` says which."""
        for k in (term.state_m, term.state_o):
            if k not in self.odom:
                raise KeyError(f"map-to-map term refers to keyframe {k}, not in the pose graph")
        f, gate = term.gated_build(_sym(term.state_m), _sym(term.state_o), self.estimate[term.state_m],
                                   self.estimate[term.state_o])
        self.last_map_to_map_reason = gate.reason
        if f is None:
            return False
        self.graph.add(f)
        self.map_to_map.append(term)
        return True

    def optimise(self, max_iterations: int = 50, relative_tol: float = 1e-6) -> dict[int, np.ndarray]:
        """Solve; the result becomes the initial guess of the next solve. Returns key -> corrected T_WS.

        Iterates one LM step at a time and yields between steps: gtsam keeps Python's GIL while it computes, so
        another thread (the estimator's) waits at most one step, not a whole solve."""
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(max_iterations)
        opt = gtsam.LevenbergMarquardtOptimizer(self.graph, self.initial, params)
        err = opt.error()
        for _ in range(max_iterations):
            opt.iterate()
            new = opt.error()
            time.sleep(0)
            if err - new <= relative_tol * max(err, 1e-12):
                break
            err = new
        values = opt.values()
        self.initial = values
        self.estimate = {k: values.atPose3(_sym(k)).matrix() for k in (*self.fixed, *self.keys)}
        return dict(self.estimate)

    def correction(self) -> np.ndarray:
        """T_W'W: maps the window's (odometry) frame to the corrected frame at the newest node."""
        if not self.keys:
            return self._T_session.copy()
        k = self.keys[-1]
        return self.estimate[k] @ inv_T(self.odom[k])
