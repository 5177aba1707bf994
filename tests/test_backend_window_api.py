"""The estimator's window is read and written only through its public API (services/backend/window/estimator.py): nothing
outside estimator.py touches ``est._*``; the read API answers what initialisation and loop closure need, and the
collaborators given to the constructor are called (extra factors every optimisation, listeners before each
marginalisation)."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
from gtsam.symbol_shorthand import X

import vio_sim as sim
from services.backend.config import BackendConfig
from services.backend.window.estimator import WindowedVioEstimator
from shared.vio.cameras import VioCamera

ROOT = next(p for p in Path(__file__).resolve().parents if (p / "pyproject.toml").exists())
ESTIMATOR_NAMES = {"est", "estimator"}  # how the code base names a WindowedVioEstimator


def _private_estimator_accesses(source: str, name: str) -> list[str]:
    """``est._x``, ``estimator._x``, ``<anything>.estimator._x`` in one file's ``source`` (dunders are fine)."""
    hits = []
    for node in ast.walk(ast.parse(source, name)):
        if not (isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__")):
            continue
        v = node.value
        if (isinstance(v, ast.Name) and v.id in ESTIMATOR_NAMES) or (isinstance(v, ast.Attribute) and v.attr == "estimator"):
            hits.append(f"{name}:{node.lineno}: .{node.attr}")
    return hits


def test_nothing_outside_the_estimator_touches_its_private_fields():
    own = ROOT / "services" / "backend" / "window" / "estimator.py"
    files = [p for d in ("services", "tools", "tests", "examples") for p in sorted((ROOT / d).rglob("*.py")) if p != own]
    assert len(files) > 100
    hits = [h for p in files for h in _private_estimator_accesses(p.read_text(), str(p.relative_to(ROOT)))]
    assert hits == [], "use the estimator's read API instead:\n" + "\n".join(hits)
    # the check finds what it is for
    probe = "x = est._obs\ny = self.shell.estimator._priors\nz = est.__class__\nw = self._obs\n"
    assert _private_estimator_accesses(probe, "probe") == ["probe:1: ._obs", "probe:2: ._priors"]


class _Extra:
    def __init__(self):
        self.calls = 0

    def window_factors(self, est):
        self.calls += 1
        return []


class _Listener:
    def __init__(self):
        self.seen = []

    def on_marginalise(self, est, old, new):
        # while the window still holds both: their observations, the IMU factor between them, their joint marginal
        assert old in est.stamps and new in est.stamps and est.keyframes[:2] == [old, new]
        assert est.imu_factor_to(new) is not None and est.imu_factor_to(old) is None
        cov = est.joint_marginal([X(old), X(new)])
        self.seen.append((old, new, cov is not None and cov.shape == (12, 12) and bool(np.all(np.isfinite(cov)))))


def test_read_api_and_constructor_collaborators():
    rng = np.random.default_rng(1)
    tr, cams, pts = sim.Trajectory(), sim.rig(2), sim.landmarks_cylinder(300, seed=2)
    extra, listener = _Extra(), _Listener()
    est = WindowedVioEstimator(BackendConfig(window_keyframes=4),
                               [VioCamera(c.T_SC, c.undistort, c.K[0, 0]) for c in cams],
                               extra_factors=[extra], on_marginalise=[listener])
    st, om, ac = sim.imu(tr, 0.0, 2.1, 200.0)
    t0 = 0.5
    T0 = tr.T_WS(np.array([t0]))[0]
    est.initialise(int(t0 * 1e9), T0[:3, :3], tr.velocity(np.array([t0]))[0], np.zeros(3), np.zeros(3),
                   static=True, p_W=T0[:3, 3])
    j, frames = 0, 0
    for t in np.arange(t0, 2.0, 0.1):
        stamp = int(round(t * 1e9))
        while j < len(st) and st[j] <= stamp:
            est.add_imu(st[j], om[j], ac[j])
            j += 1
        ids, c, uv = sim.observe(tr.T_WS(np.array([t]))[0], pts, cams, 0.5, rng, 40)
        est.process_frame(stamp, ids, c, uv, is_keyframe=True)
        frames += 1
    assert extra.calls >= frames  # every window graph (and its rebuilds) asked the source
    assert len(listener.seen) == frames - 4 and all(ok for _, _, ok in listener.seen)
    assert [old for old, _, _ in listener.seen] == sorted(old for old, _, _ in listener.seen)

    n = est.keyframes[-1]
    obs = est.observations_of(n)
    assert len(obs) > 20 and all(len(o) >= 1 and o[0][0] in (0, 1) and o[0][1].shape == (2,) for o in obs.values())
    obs.clear()  # a new dict each time
    assert len(est.observations_of(n)) > 20
    in_graph = [lm for lm in est.observations_of(n) if est.landmark_in_graph(lm)]
    assert len(in_graph) > 10 and not est.landmark_in_graph(-1)
    f, T_SC = est.focal_px, est.T_SC
    assert f.shape == (2,) and T_SC.shape == (2, 4, 4) and np.allclose(T_SC[0], cams[0].T_SC)
    f[:] = 0.0  # copies
    assert np.all(est.focal_px > 0)
    assert not est.mono_pending  # two cameras: metric from the start

    est.forget_triangulations()
    assert not any(est.landmark_in_graph(lm) for lm in in_graph) and est.window_counts()["landmarks"] == 0
    assert len(est.observations_of(n)) > 20  # the observations stay
