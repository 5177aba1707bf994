"""Ground-truth / trajectory file IO: EuRoC state_groundtruth_estimate0 CSV, EuRoC-style pose CSV, TUM.

A trajectory is a :class:`PoseSeries`: ``stamps_ns`` int64 (N,), ``p_WS`` float64 (N, 3) positions and
``q_WS_wxyz`` float64 (N, 4) Hamilton unit quaternions (w, x, y, z) of the body S in the world W.
Optional ``v_WS`` (N, 3) velocities (EuRoC ground truth carries them).
"""
from __future__ import annotations

import lzma
from dataclasses import dataclass
from pathlib import Path

import numpy as np


class TrajectoryFileError(ValueError):
    """A trajectory file is missing or malformed; the message names the file and the problem."""


@dataclass(frozen=True)
class PoseSeries:
    stamps_ns: np.ndarray  # int64 (N,)
    p_WS: np.ndarray  # float64 (N, 3) [m]
    q_WS_wxyz: np.ndarray  # float64 (N, 4) Hamilton, w first
    v_WS: np.ndarray | None = None  # float64 (N, 3) [m/s] or None
    gyro_bias: np.ndarray | None = None  # float64 (N, 3) [rad/s] (17-column EuRoC ground truth) or None
    acc_bias: np.ndarray | None = None  # float64 (N, 3) [m/s^2] (17-column EuRoC ground truth) or None

    def __len__(self) -> int:
        return int(self.stamps_ns.shape[0])


def _open_text(path: Path):
    if not path.is_file():
        raise TrajectoryFileError(f"{path}: file not found")
    if path.suffix == ".xz":
        return lzma.open(path, "rt")
    return open(path, "r")


def _load_rows(path: Path, delimiter: str | None, ncols: tuple[int, ...]) -> np.ndarray:
    rows = []
    with _open_text(path) as f:
        for lineno, line in enumerate(f, start=1):
            s = line.strip()
            if not s or s.startswith("#"):
                continue
            parts = s.split(delimiter) if delimiter else s.split()
            if len(parts) not in ncols:
                raise TrajectoryFileError(
                    f"{path}:{lineno}: expected {' or '.join(map(str, ncols))} columns, got {len(parts)}")
            try:
                rows.append([float(p) for p in parts] if delimiter is None else parts)
            except ValueError as e:
                raise TrajectoryFileError(f"{path}:{lineno}: not a number ({e})") from None
    if not rows:
        raise TrajectoryFileError(f"{path}: no data rows")
    return rows


def _check_monotonic(path: Path, stamps: np.ndarray) -> None:
    bad = np.nonzero(np.diff(stamps) <= 0)[0]
    if bad.size:
        i = int(bad[0]) + 1
        raise TrajectoryFileError(
            f"{path}: timestamps not strictly increasing at data row {i} ({stamps[i]} after {stamps[i - 1]})")


def _normalised(q: np.ndarray, path: Path) -> np.ndarray:
    n = np.linalg.norm(q, axis=1, keepdims=True)
    if np.any(n < 1e-9):
        raise TrajectoryFileError(f"{path}: zero quaternion at data row {int(np.argmin(n[:, 0]))}")
    return q / n


def read_euroc_csv(path: str | Path) -> PoseSeries:
    """Read EuRoC ground truth (17 columns) or EuRoC-style pose CSV (8 columns: t_ns, p xyz, q wxyz)."""
    path = Path(path)
    rows = _load_rows(path, ",", (8, 17))
    widths = {len(r) for r in rows}
    if len(widths) != 1:
        raise TrajectoryFileError(f"{path}: rows have differing column counts {sorted(widths)}")
    try:
        stamps = np.array([int(r[0]) for r in rows], dtype=np.int64)
        data = np.array([[float(x) for x in r[1:]] for r in rows], dtype=np.float64)
    except ValueError as e:
        raise TrajectoryFileError(f"{path}: not a number ({e})") from None
    _check_monotonic(path, stamps)
    full = data.shape[1] == 16  # 17 columns: velocity and biases too
    return PoseSeries(stamps, data[:, 0:3].copy(), _normalised(data[:, 3:7], path),
                      data[:, 7:10].copy() if full else None, data[:, 10:13].copy() if full else None,
                      data[:, 13:16].copy() if full else None)


def read_tum(path: str | Path) -> PoseSeries:
    """Read a TUM file: ``t[s] x y z qx qy qz qw`` per line (whitespace separated)."""
    path = Path(path)
    rows = []
    stamps_l = []
    with _open_text(path) as f:
        for lineno, line in enumerate(f, start=1):
            s = line.strip()
            if not s or s.startswith("#"):
                continue
            parts = s.split()
            if len(parts) != 8:
                raise TrajectoryFileError(f"{path}:{lineno}: expected 8 columns, got {len(parts)}")
            try:
                stamps_l.append(_seconds_to_ns(parts[0]))
                rows.append([float(x) for x in parts[1:]])
            except ValueError as e:
                raise TrajectoryFileError(f"{path}:{lineno}: not a number ({e})") from None
    if not rows:
        raise TrajectoryFileError(f"{path}: no data rows")
    a = np.column_stack([np.zeros(len(rows)), np.asarray(rows, dtype=np.float64)])
    stamps = np.asarray(stamps_l, dtype=np.int64)
    _check_monotonic(path, stamps)
    q = a[:, [7, 4, 5, 6]]
    return PoseSeries(stamps, a[:, 1:4].copy(), _normalised(q, path))


def _seconds_to_ns(text: str) -> int:
    """Exact decimal seconds -> int ns (float64 cannot hold ns at epoch-scale seconds)."""
    whole, _, frac = text.partition(".")
    if "e" in text.lower():
        return int(round(float(text) * 1e9))
    sign = -1 if whole.startswith("-") else 1
    return sign * (abs(int(whole or "0")) * 10**9 + int((frac + "000000000")[:9]))


def _comment_lines(comment: str) -> str:
    return "".join(f"# {line}\n" for line in comment.splitlines())


def write_tum(path: str | Path, poses: PoseSeries, comment: str = "") -> None:
    """Write TUM with exact ns stamps (``sec.nnnnnnnnn``); ``comment``: lines written first, each after ``# ``
    (e.g. the frame the poses are in)."""
    with open(path, "w") as f:
        f.write(_comment_lines(comment) + "# t[s] x y z qx qy qz qw\n")
        for t, p, q in zip(poses.stamps_ns, poses.p_WS, poses.q_WS_wxyz[:, [1, 2, 3, 0]]):
            t = int(t)
            f.write(f"{t // 10**9}.{t % 10**9:09d} " + " ".join(f"{x:.9f}" for x in (*p, *q)) + "\n")


def write_euroc_csv(path: str | Path, poses: PoseSeries, comment: str = "") -> None:
    """Write EuRoC-style pose CSV: t_ns, p xyz [m], q wxyz; ``comment`` as in :func:`write_tum`."""
    with open(path, "w") as f:
        f.write(_comment_lines(comment) + "#timestamp [ns], p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], "
                "q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z []\n")
        for t, p, q in zip(poses.stamps_ns, poses.p_WS, poses.q_WS_wxyz):
            f.write(f"{int(t)}," + ",".join(f"{x:.9f}" for x in (*p, *q)) + "\n")


def read_trajectory(path: str | Path) -> PoseSeries:
    """Read by format: ``.txt``/``.tum`` -> TUM, otherwise EuRoC CSV (``.csv``); either may be xz-compressed."""
    name = Path(path).name.removesuffix(".xz")
    if name.endswith((".txt", ".tum")):
        return read_tum(path)
    return read_euroc_csv(path)


def series_from_matrices(stamps_ns, T_WS) -> PoseSeries:
    """A PoseSeries from stamps (N,) [ns] and body poses T_WS (N, 4, 4)."""
    from shared.geometry import R_to_quat_wxyz

    T = np.asarray(T_WS, dtype=np.float64).reshape(-1, 4, 4)
    return PoseSeries(np.asarray(stamps_ns, dtype=np.int64).reshape(-1), T[:, :3, 3].copy(),
                      R_to_quat_wxyz(T[:, :3, :3]).reshape(-1, 4))
