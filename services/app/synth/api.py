"""Replicas on demand: generated once, cached under ``shared.paths.data_dir()/replicas/<name>``.

::

    from services.app.synth.api import ensure_replica, ensure_default_replica
    path = ensure_replica("V1_02", "vicon-a", imu="real", duration_s=10.0)   # -> .../replicas/V1_02-vicon-a-real-s0-d10-seed0
    path = ensure_default_replica()                                          # the bundled 25 s V1_02 replica

Generation goes into ``<name>.partial`` and is renamed when complete, so an interrupted run never
leaves a half replica behind; a file lock makes concurrent callers (several tests, several
processes) wait for one generator instead of rendering twice.
"""
from __future__ import annotations

import dataclasses
import fcntl
import logging
import shutil
from pathlib import Path

import yaml

from shared.paths import data_dir
from services.app.synth.profiles import apply_profile
from services.app.synth.render import RenderConfig
from services.app.synth.replica import GENERATOR_VERSION, ReplicaSpec, generate

log = logging.getLogger(__name__)

DEFAULT = dict(sequence="V1_02", scene="vicon-a", imu="real", duration_s=25.0, start_s=0.0, seed=0)


def replica_name(spec: ReplicaSpec) -> str:
    def num(x: float) -> str:
        return f"{x:g}".replace(".", "p")

    dur = num(spec.duration_s) if spec.duration_s > 0 else "all"
    return f"{spec.sequence or 'custom'}-{spec.scene}-{spec.imu}-s{num(spec.start_s)}-d{dur}-seed{spec.seed}"


def _current(folder: Path) -> bool:
    """Whether ``folder`` holds a complete replica made by this generator version."""
    try:
        info = yaml.safe_load((folder / "replica.yaml").read_text()) or {}
    except (OSError, yaml.YAMLError):
        return False
    return isinstance(info, dict) and info.get("generator_version", 1) == GENERATOR_VERSION


def ensure_spec(spec: ReplicaSpec, root: Path | None = None, progress: bool = True, profile: str = "") -> Path:
    """Path of the replica of ``spec`` (default render settings, or those of ``profile``:
    services/app/synth/profiles.py), generating it if absent."""
    plain = dataclasses.replace(spec, render=RenderConfig(), timeshift_cam_imu_s=0.0)
    if (spec != apply_profile(plain, profile) or spec.groundtruth or spec.imu_data or spec.image_timestamps
            or spec.calib):
        raise ValueError("ensure_replica caches only known sequences with default render settings or a named "
                         "profile; use generate()")
    root = Path(root) if root is not None else data_dir() / "replicas"
    root.mkdir(parents=True, exist_ok=True)
    final = root / (replica_name(spec) + (f"-{profile}" if profile else ""))
    if _current(final):
        return final
    with open(root / f".{final.name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # another process may be generating it: wait for it
        if _current(final):
            return final
        if final.exists():
            log.warning("replica %s was made by an older generator (replica.yaml generator_version < %d): "
                        "making it again", final, GENERATOR_VERSION)
            shutil.rmtree(final)
        partial = root / f"{final.name}.partial"
        shutil.rmtree(partial, ignore_errors=True)
        log.info("generating replica %s (once; cached)", final)
        generate(spec, partial, progress=progress)
        partial.rename(final)
    return final


def ensure_replica(sequence: str = "V1_02", scene: str = "vicon-a", imu: str = "real", duration_s: float = 0.0,
                   start_s: float = 0.0, seed: int = 0, depth_cameras: tuple[int, ...] = (0,),
                   root: Path | None = None, progress: bool = True, profile: str = "") -> Path:
    """Replica folder (holding ``mav0/``) of a known EuRoC sequence in a scene, with the settings of ``profile``
    ('' = defaults; services/app/synth/profiles.py); generated on first use."""
    spec = ReplicaSpec(scene=scene, sequence=sequence, imu=imu, start_s=start_s, duration_s=duration_s, seed=seed,
                       depth_cameras=list(depth_cameras))
    return ensure_spec(apply_profile(spec, profile), root, progress, profile)


def dataset_or_replica(path: str | Path | None = None, seconds: float = 0.0) -> Path:
    """``path`` when given; else a replica of the first ``seconds`` of V1_02 in 'vicon-a' (real IMU), or the bundled
    default when ``seconds`` is 0: generated on first use, then cached."""
    if path:
        return Path(path)
    if seconds:
        return ensure_replica("V1_02", "vicon-a", imu="real", duration_s=seconds)
    return ensure_default_replica()


def replica_exists(root: Path | None = None, **spec) -> bool:
    """Whether the replica of ``spec`` (default: the bundled default) is already generated and cached."""
    spec = ReplicaSpec(**{**DEFAULT, **spec})
    root = Path(root) if root is not None else data_dir() / "replicas"
    return _current(root / replica_name(spec))


def ensure_default_replica(progress: bool = True) -> Path:
    """The bundled default: 25 s of V1_02 in 'vicon-a' with the real IMU (about 500 stereo frames)."""
    return ensure_replica(**DEFAULT, progress=progress)
