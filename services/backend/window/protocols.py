"""The back end's seams: what its parts take from one another, each handed over in a constructor.

:class:`services.backend.node.BackendNode` (the composition root) builds the parts and passes each its
collaborators; no part installs a hook into another after construction.

* :class:`ExtraFactorSource`: factors the windowed estimator adds to every window graph (the occupancy-to-point
  terms, services/backend/o2p/terms.py);
* :class:`MarginalisationListener`: told before the estimator marginalises its oldest keyframe (the keyframe
  history of the loop closer, services/backend/loop/history.py);
* :class:`SubmapAnchoring`: how the occupancy terms tie a submap to a keyframe and map published poses back into
  the window's frame (the loop closure's published frame, services/backend/loop/published_frame.py; none without a loop
  closer).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol

import gtsam
import numpy as np

if TYPE_CHECKING:
    from services.backend.window.estimator import WindowedVioEstimator


class ExtraFactorSource(Protocol):
    def window_factors(self, est: WindowedVioEstimator) -> list[gtsam.NonlinearFactor]:
        """Factors added to the graph of ``est``'s window at every optimisation; they may only use the window's
        X (pose) keys."""
        ...


class MarginalisationListener(Protocol):
    def on_marginalise(self, est: WindowedVioEstimator, old: int, new: int) -> None:
        """Keyframe state ``old`` is about to leave ``est``'s window and ``new`` becomes its oldest keyframe; the
        window's marginals (:meth:`WindowedVioEstimator.joint_marginal`) still cover both."""
        ...


class SubmapAnchoring(Protocol):
    def anchor_of(self, stamp_ns: int, T_WM: np.ndarray) -> tuple[int, np.ndarray] | None:
        """The keyframe a submap created at ``stamp_ns`` with pose ``T_WM`` (in the published frame W') follows:
        (its state index, ``T_KM`` = the submap's frame in that keyframe's body frame); None when no keyframe is
        near its creation."""
        ...

    def correction(self) -> np.ndarray | None:
        """T_W'W: the published frame W' (where depth poses and submap poses arrive) relative to the window's
        frame W; None when they are the same frame."""
        ...
