"""MVS with and without the landmark prior on the same frames: replays a `sigmaslam run --record` recording of a
replica (estimator states, keyframes, landmarks as the depth service saw them) through
:class:`services.depth.pipeline.DepthPipeline` and compares both MVS outputs (and their fusion with stereo)
with the ground-truth depth ray-cast from the replica's scene mesh at the ground-truth pose.

    python -m tools.depth.prior_ab REPLICA RUN/recording.mcap [--frames 20 --stride 10 --skip 40]

Causal like the service: a frame uses the keyframe poses and the landmarks published at or before its time.
"""
from __future__ import annotations

import argparse
import sys

import numpy as np

from services.depth.config import DepthConfig
from services.depth.pipeline import DepthPipeline
from services.depth.uncertainty import depth_metrics, fuse
from services.recorder.mcap_reader import read_recording
from shared.camera import load_rig


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("replica", help="replica folder (EuRoC layout with scene/mesh.ply and ground truth)")
    ap.add_argument("recording", help="MCAP of a `sigmaslam run REPLICA --record` (estimator topics)")
    ap.add_argument("--frames", type=int, default=20, help="frames evaluated")
    ap.add_argument("--stride", type=int, default=10, help="every n-th estimator state")
    ap.add_argument("--skip", type=int, default=40, help="states skipped at the start")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--max-age", type=float, default=DepthConfig().prior_max_age_s, help="depth.prior_max_age_s [s]")
    ap.add_argument("--max-points", type=int, default=DepthConfig().prior_max_points, help="depth.prior_max_points")
    a = ap.parse_args(argv)

    import open3d as o3d

    from shared.euroc import read_euroc_csv
    from shared.euroc_reader import EurocDataset
    from services.app.synth.trajectory import Trajectory

    states, kfs, lms = {}, [], []
    for key, _t, msg in read_recording(a.recording):
        if key.endswith("estimator/state") and msg.status == "tracking":
            states[int(msg.header.stamp_ns)] = msg.T_WS
        elif key.endswith("estimator/keyframes"):
            kfs.append(msg)
        elif key.endswith("estimator/landmarks"):
            lms.append(msg)
    if not lms:
        print(f"{a.recording}: no estimator/landmarks messages", file=sys.stderr)
        return 2
    cams = {c.name: c for c in load_rig(a.replica)}
    pipe = DepthPipeline(DepthConfig(threads=a.threads, device="cpu", prior_max_age_s=a.max_age,
                                   prior_max_points=a.max_points), cams["cam0"], cams["cam1"])
    if pipe.mvs_net is None:
        print("no MVS weights", file=sys.stderr)
        return 2
    ds = EurocDataset(a.replica)
    traj = Trajectory(read_euroc_csv(ds.groundtruth_path), knot_spacing_s=0.05)
    mesh = o3d.io.read_triangle_mesh(str(ds.root / "scene" / "mesh.ply"))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    h, w = pipe.cfg.height, pipe.cfg.width
    v, u = np.mgrid[0:h, 0:w]
    rays = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], 1) @ np.linalg.inv(pipe.K).T  # z = 1
    names = ds.camera_names
    stamps = sorted(states)
    todo = stamps[a.skip::a.stride][:a.frames]
    from tools.depth.train import prior_points

    rng = np.random.default_rng(0)
    acc: dict[str, list] = {"mvs_prior": [], "mvs_no_prior": [], "mvs_gt_prior": [], "fused_prior": [],
                            "fused_no_prior": []}
    n_prior, n_src, k_kf, seen, rel_err = [], [], 0, set(), []
    for t in todo:
        while k_kf < len(kfs) and kfs[k_kf].header.stamp_ns <= t:  # keyframe poses known at t
            kf = kfs[k_kf]
            for s in kf.stamps_ns.tolist():
                if s not in seen and s <= t:
                    seen.add(s)
                    pipe.remember_frame(s, ds.load_frame(s)[names.index("cam0")])
            pipe.update_keyframes(kf.stamps_ns, kf.T_WS)
            k_kf += 1
        prev = [m for m in lms if m.header.stamp_ns <= t]
        if not prev:
            continue
        lm = prev[-1]
        pipe.update_landmarks(lm.p_W, lm.last_seen_ns, lm.num_observations)
        imgs = ds.load_frame(t)
        left, right = pipe.rect.rectify(imgs[names.index("cam0")], imgs[names.index("cam1")])
        T_WC = states[t] @ pipe.T_SC
        prior = pipe.mvs_prior(t, T_WC)
        with_p, ns = pipe.mvs(left, T_WC, prior)
        without, _ = pipe.mvs(left, T_WC, None)
        if with_p is None:
            continue
        stereo = pipe.stereo(left, right)
        T_gt = traj.pose(np.array([t]))[0] @ pipe.T_SC
        dirs = rays @ T_gt[:3, :3].T
        hit = scene.cast_rays(o3d.core.Tensor(np.hstack([np.tile(T_gt[:3, 3], (len(dirs), 1)), dirs]).astype(np.float32)))
        gt = hit["t_hit"].numpy().reshape(h, w).astype(np.float32)
        gt[~np.isfinite(gt)] = np.nan
        # the training's simulated prior on the same frame: as many GT pixels as landmark pixels, 2 % noise
        n = int(np.count_nonzero(prior)) if prior is not None else 0
        gt_prior = prior_points(rng, gt, n)
        acc["mvs_gt_prior"].append((*pipe.mvs(left, T_WC, gt_prior)[0], gt))
        if prior is not None:
            m = (prior > 0) & np.isfinite(gt)
            rel_err.append(np.abs(prior[m] - gt[m]) / gt[m])
        acc["mvs_prior"].append((*with_p, gt))
        acc["mvs_no_prior"].append((*without, gt))
        acc["fused_prior"].append((*fuse(*stereo, *with_p), gt))
        acc["fused_no_prior"].append((*fuse(*stereo, *without), gt))
        n_prior.append(int(np.count_nonzero(prior)) if prior is not None else 0)
        n_src.append(ns)
    if not n_prior:
        print("no frame with MVS source views", file=sys.stderr)
        return 2
    print(f"{len(n_prior)} frames, {np.mean(n_src):.1f} MVS sources on average, prior pixels per frame: min "
          f"{min(n_prior)} median {np.median(n_prior):.0f} mean {np.mean(n_prior):.1f} max {max(n_prior)}")
    e = np.concatenate(rel_err) if rel_err else np.zeros(0)
    if len(e):
        print(f"landmark prior depth against ground truth: relative error median {np.median(e):.4f}, 90 % "
              f"{np.percentile(e, 90):.4f}, > 10 %: {np.mean(e > 0.1):.3f} of {len(e)} pixels "
              "(training simulated 2 % Gaussian noise)\n")
    print("| method | AbsRel | RMSE [m] | d<1.25 | mean Mahalanobis | NLL (Laplace) |")
    print("|---|---|---|---|---|---|")
    for name, v in acc.items():
        d, s, g = (np.stack(x) for x in zip(*v))
        r = depth_metrics(d, s, g)
        print(f"| {name} | {r['absrel']:.4f} | {r['rmse']:.4f} | {r['delta1']:.3f} | {r['mahalanobis']:.3f} | "
              f"{r['nll_laplace']:.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
