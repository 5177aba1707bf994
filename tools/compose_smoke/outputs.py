"""What a compose run must leave behind: the mapper's mesh and submaps, the back end's map and final trajectory.

The back end publishes its final (non-causal) trajectory on ``estimator/trajectory_final`` and writes its sparse map
to ``loop.map_output`` (configs/docker.yaml: /outputs/map); the recorder keeps every message of the run in an MCAP
file, where the final trajectory and the count of frames played and of states published are read back.
"""

from __future__ import annotations

import re
from collections import Counter
from pathlib import Path

NAMESPACE = "sigmaslam/robot0"  # configs/docker.yaml


def frames_sent(player_log: str) -> int | None:
    """The camera frames the player sent, from its closing line (``player: 501 frames sent ...``)."""
    m = re.search(r"player: (\d+) frames sent", player_log)
    return int(m[1]) if m else None


def recording_figures(path: Path, namespace: str = NAMESPACE) -> dict:
    """Messages per topic of interest, and the final trajectory's length, from a recording."""
    from mcap.reader import make_reader

    from services.recorder.mcap_reader import read_recording

    wanted = {f"{namespace}/{t}": t for t in ("sensors/frame", "estimator/state", "depth/stereo", "map/submap",
                                               "estimator/trajectory_final")}
    counts: Counter = Counter()
    with open(path, "rb") as f:
        for _schema, channel, _message in make_reader(f).iter_messages(topics=list(wanted)):
            counts[wanted[channel.topic]] += 1
    final = [m for _, _, m in read_recording(path, [f"{namespace}/estimator/trajectory_final"])]
    stats = [m for _, _, m in read_recording(path, [f"{namespace}/stats/frontend"])]
    dropped = None  # the frames the frontend left out (its queue's drops and catch-up skips), from its last stats
    if stats and "sensors/frame" in stats[-1].queue_names:
        dropped = int(stats[-1].queue_dropped[list(stats[-1].queue_names).index("sensors/frame")])
    return {"frames_recorded": counts["sensors/frame"], "states_recorded": counts["estimator/state"],
            "frontend_frames_dropped": dropped,
            "depth_frames": counts["depth/stereo"], "submap_messages": counts["map/submap"],
            "final_trajectory_poses": len(final[-1].stamps_ns) if final else 0,
            "final_keyframes": int(final[-1].keyframes) if final else 0}


def check(outputs: Path, recordings: Path) -> tuple[list[str], dict]:
    """(problems, figures) of the run's folders; no problems when all that is asked for is there. The counts of depth
    frames and submap meshes in the recording are figures only: the mapper publishes its last meshes while the
    stack stops, after the recorder may have."""
    problems: list[str] = []
    run = outputs / "map"
    mesh, submaps, sparse = run / "mesh.ply", sorted((run / "submaps").glob("*.ply")), run / "map" / "sparse.npz"
    figures: dict = {"mesh_bytes": mesh.stat().st_size if mesh.is_file() else 0, "submap_meshes": len(submaps),
                     "sparse_map": sparse.is_file()}
    if figures["mesh_bytes"] < 10_000:
        problems.append(f"the mapper's mesh {mesh}: {figures['mesh_bytes']} bytes (expected a map, > 10 kB)")
    if not submaps:
        problems.append(f"the mapper wrote no submap meshes in {run / 'submaps'}")
    if not sparse.is_file():
        problems.append(f"the back end wrote no sparse map {sparse}")
    files = sorted(recordings.glob("*.mcap"), key=lambda p: p.stat().st_mtime)
    if not files:
        problems.append(f"the recorder wrote nothing in {recordings}")
        return problems, figures
    figures["recording"] = str(files[-1])
    figures["recording_bytes"] = files[-1].stat().st_size
    figures.update(recording_figures(files[-1]))
    if figures["final_trajectory_poses"] == 0:
        problems.append("no final trajectory from the back end (estimator/trajectory_final) in the recording")
    return problems, figures
