"""``sigmaslam map info DIR``, ``sigmaslam map merge A B OUT``, ``sigmaslam map grid DIR`` and ``sigmaslam map
export DIR``: saved maps (docs/maps.md; grid and export: services/app/map_occupancy_cmd.py, docs/occupancy.md).

A saved map is the folder ``DIR/map/`` every ``sigmaslam run --out DIR`` writes (shared/map_folder.py): the back
end's ``sparse.npz`` (keyframes, features, landmarks, pose graph: services/backend/loop/saved_map.py) and the
mapping's ``dense.npz`` (occupancy submaps: services/mapping/io.py). DIR may be the run folder or its map/ folder.

- ``info`` prints what a map holds (``--json`` for the numbers as JSON).
- ``merge`` finds where B lies in A (services/backend/loop/map_merge.py: place recognition and PnP of B's keyframes
  against A's), moves B into A's frame and writes both as one map to ``OUT/map/``: A's keyframes and submaps as they
  were, B's after them (new ids) with the shared places as loop edges. Maps that share no verified place are not
  merged (exit status 1).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from shared.map_folder import DENSE_FILE, SPARSE_FILE, dense_path, run_map_dir, sparse_path


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="map_command", metavar="ACTION", required=True)
    q = sub.add_parser("info", help="print what a saved map holds", description="print what a saved map holds")
    q.add_argument("dir", help="a run's output folder, or its map/ folder")
    q.add_argument("--json", action="store_true", help="print the numbers as JSON")
    q = sub.add_parser("merge", help="merge map B into map A's frame where they share a place",
                       description="merge map B into map A's frame where they share a place")
    q.add_argument("a", help="the first map (its frame is the merged map's)")
    q.add_argument("b", help="the second map, moved into A's frame")
    q.add_argument("out", help="output folder: the merged map goes to OUT/map/")
    q.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a loop.* config field of the matching (e.g. loop.relocalise_confirmations=3)")
    from services.app.map_occupancy_cmd import add_parsers

    add_parsers(sub)


def _dense_summary(path: Path) -> dict | None:
    from services.mapping.io import load_map

    if not path.is_file():
        return None
    mapper = load_map(path)
    poses = np.array([sm.T_WM[:3, 3] for sm in mapper.submaps]).reshape(-1, 3)
    return {"submaps": len(mapper.submaps), "voxel_size_m": mapper.sensor.voxel_size_m,
            "blocks": int(sum(sm.store.n_blocks for sm in mapper.submaps)), "bytes": int(mapper.nbytes()),
            "frames_integrated": int(sum(sm.n_frames for sm in mapper.submaps)),
            "submap_origins_extent_m": [poses.min(0).tolist(), poses.max(0).tolist()] if len(poses) else None}


def map_info(folder: str | Path) -> dict:
    """What the saved map in ``folder`` holds: {"map": path, "sparse": summary or None, "dense": summary or None}."""
    from services.backend.loop.saved_map import load_sparse

    sp, dp = sparse_path(folder), dense_path(folder)
    if not sp.is_file() and not dp.is_file():
        raise FileNotFoundError(f"{folder}: no saved map (neither {sp} nor {dp})")
    return {"map": str(sp.parent), "sparse": load_sparse(sp).summary() if sp.is_file() else None,
            "dense": _dense_summary(dp)}


def _print_info(info: dict) -> None:
    print(f"saved map {info['map']}")
    s = info["sparse"]
    if s is None:
        print(f"  {SPARSE_FILE}: none (no relocalisation possible: the back end of that run did not save one)")
    else:
        print(f"  {SPARSE_FILE}: {s['keyframes']} keyframes ({s['keyframes_with_features']} with features), "
              f"{s['landmarks']} landmarks, {s['features']} features; pose graph {s['odometry_edges']} odometry and "
              f"{s['loop_edges']} loop edges; path {s['path_length_m']:.1f} m")
        if s["extent_m"]:
            lo, hi = np.round(s["extent_m"][0], 2), np.round(s["extent_m"][1], 2)
            print(f"    keyframes within {lo.tolist()} .. {hi.tolist()} m; vocabulary {s['vocabulary']}")
        for k, ses in enumerate(s["sessions"]):
            print(f"    session {k}: {ses.get('source', '?')}, {ses.get('keyframes', '?')} keyframes, started "
                  f"{ses.get('started_utc', '?')}{'' if ses.get('aligned', True) else ', not aligned'}")
    d = info["dense"]
    if d is None:
        print(f"  {DENSE_FILE}: none")
    else:
        print(f"  {DENSE_FILE}: {d['submaps']} submaps, {d['blocks']} blocks of {d['voxel_size_m']} m voxels, "
              f"{d['bytes'] / 2**20:.1f} MiB, {d['frames_integrated']} depth frames integrated")


def merge_maps(a: str | Path, b: str | Path, out: str | Path, cfg=None) -> dict:
    """Merge saved map ``b`` into ``a``'s frame and write ``out``/map/; returns what was done. Raises
    SparseMapError when the maps cannot be merged (no shared place, other vocabulary or rig)."""
    from services.backend.loop.config import LoopConfig
    from services.backend.loop.map_merge import align_maps
    from services.backend.loop.saved_map import SparseMapError, concatenate, load_sparse, save_sparse
    from services.backend.loop.vocabulary import DEFAULT_PATH, Vocabulary
    from services.mapping.io import append_submaps, load_map, save_map

    cfg = cfg or LoopConfig()
    for folder in (a, b):
        if not sparse_path(folder).is_file():
            raise FileNotFoundError(f"{folder}: no saved sparse map ({sparse_path(folder)} not found)")
    ma, mb = load_sparse(sparse_path(a)), load_sparse(sparse_path(b))
    voc = Vocabulary.load(cfg.vocabulary or DEFAULT_PATH)

    def progress(done: int, total: int) -> None:
        print(f"[map merge] {done} of {total} keyframes of B matched against A", flush=True)

    res = align_maps(ma, mb, voc, cfg, progress)
    report = {"queried": res.queried, "verified": res.verified, "agreeing": res.agreeing}
    if res.T_ab is None:
        raise SparseMapError(f"no shared place found: {res.verified} verified matches of {res.queried} keyframes, "
                             f"{res.agreeing} agreeing (loop.relocalise_confirmations = {cfg.relocalise_confirmations})")
    merged = concatenate(ma, mb, res.T_ab, res.links)
    dst = run_map_dir(out)
    save_sparse(merged, dst / SPARSE_FILE)
    report.update({"T_ab": res.T_ab.tolist(), "links": len(res.links), "keyframes": len(merged), "out": str(dst)})
    da, db = dense_path(a), dense_path(b)
    if da.is_file() and db.is_file():
        mapper = load_map(da)
        report["submaps"] = [len(mapper.submaps), append_submaps(mapper, load_map(db), res.T_ab)]
        save_map(mapper, dst / DENSE_FILE)
    return report


def main(args: argparse.Namespace) -> int:
    from services.backend.loop.saved_map import SparseMapError
    from services.mapping.io import MapFileError

    if args.map_command in ("grid", "export"):
        from services.app.map_occupancy_cmd import main as occupancy_main

        return occupancy_main(args)
    if args.map_command == "info":
        try:
            info = map_info(args.dir)
        except (FileNotFoundError, SparseMapError, MapFileError) as exc:
            print(f"sigmaslam map info: {exc}", file=sys.stderr)
            return 2
        print(json.dumps(info, indent=1)) if args.json else _print_info(info)
        return 0
    from services.app.system_config import load_system_config

    cfg = load_system_config(None, args.set).loop
    try:
        rep = merge_maps(args.a, args.b, args.out, cfg)
    except FileNotFoundError as exc:
        print(f"sigmaslam map merge: {exc}", file=sys.stderr)
        return 2
    except (SparseMapError, MapFileError) as exc:
        print(f"sigmaslam map merge: not merged: {exc}", file=sys.stderr)
        return 1
    t = np.asarray(rep["T_ab"])[:3, 3]
    print(f"[map merge] B lies in A at t = {np.round(t, 3).tolist()} m ({rep['agreeing']} agreeing matches of "
          f"{rep['verified']} verified, {rep['queried']} keyframes of B queried); wrote {rep['out']}: "
          f"{rep['keyframes']} keyframes" + (f", submaps {rep['submaps'][0]} + {rep['submaps'][1]}"
                                             if "submaps" in rep else ""), flush=True)
    return 0
