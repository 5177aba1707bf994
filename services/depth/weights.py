"""Network weights with their provenance: ``<name>.pt`` (a torch state dict) beside ``<name>.json``
(architecture arguments, calibration gain, training command, data, seed, time, figures).

Other weights load through the same interface as long as the state dict fits the architecture named in
the JSON (``arch``: 'stereo', 'stereo_refine' or 'mvs', ``arch_args``: constructor keyword arguments).
"""
from __future__ import annotations

import contextlib
import json
from pathlib import Path

import torch

from shared.paths import REPO_ROOT

WEIGHTS_DIR = REPO_ROOT / "services" / "depth" / "weights"
# the stereo network a config gets unless it names one: the SGBM-guided network, which holds on real photographs
# and since 2026-12-07 also gives the better map on two of three replicas (docs/depth.md)
DEFAULT_STEREO = "stereo_refine.pt"


class WeightsError(RuntimeError):
    """Missing or unusable weights; the message names the file."""


def weights_path(value: str, default_name: str) -> Path:
    """The weights file a ``depth.*_weights`` setting names: '' -> the shipped ``default_name``; a bare file name
    (no folder) -> that file among the shipped weights (``stereo_refine.pt``), unless it exists where the command
    runs; any other value -> that path as given."""
    if not value:
        return WEIGHTS_DIR / default_name
    path = Path(value)
    if path.parent == Path(".") and not path.exists():
        return WEIGHTS_DIR / path.name
    return path


def build(arch: str, arch_args: dict) -> torch.nn.Module:
    if arch == "stereo":
        from services.depth.stereo_net import StereoNet

        return StereoNet(**arch_args)
    if arch == "stereo_refine":
        from services.depth.refine_net import RefineStereoNet

        return RefineStereoNet(**arch_args)
    if arch == "mvs":
        from services.depth.mvs_net import MVSNet

        return MVSNet(**arch_args)
    raise WeightsError(f"unknown architecture {arch!r} (stereo, stereo_refine, mvs)")


def save(model: torch.nn.Module, path: str | Path, arch: str, arch_args: dict, meta: dict) -> Path:
    path = Path(path).with_suffix(".pt")
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(model.state_dict(), path)
    path.with_suffix(".json").write_text(json.dumps({"arch": arch, "arch_args": arch_args, **meta}, indent=1))
    return path


def read_meta(path: str | Path) -> dict:
    meta_path = Path(path).with_suffix(".json")
    if not meta_path.is_file():
        raise WeightsError(f"{meta_path}: provenance/architecture JSON not found")
    return json.loads(meta_path.read_text())


def load(path: str | Path, device: str = "cpu") -> tuple[torch.nn.Module, dict]:
    """(model in eval mode, its JSON metadata incl. 'gain' (1.0 if uncalibrated))."""
    path = Path(path).with_suffix(".pt")
    if not path.is_file():
        raise WeightsError(f"{path}: weights not found (train them: python -m tools.depth.train --help)")
    meta = read_meta(path)
    model = build(meta["arch"], meta.get("arch_args", {}))
    try:
        model.load_state_dict(torch.load(path, map_location=device, weights_only=True))
    except RuntimeError as exc:
        raise WeightsError(f"{path}: does not fit architecture {meta['arch']}: {exc}") from exc
    meta.setdefault("gain", 1.0)
    model = model.to(device).eval()
    if device == "cpu":  # oneDNN's convolutions are faster on NHWC tensors (same results to float rounding)
        model = model.to(memory_format=torch.channels_last)
    return model, meta


def cpu_has_fast_bfloat16() -> bool:
    """Whether this CPU computes bfloat16 natively (AMX or AVX512-BF16, from /proc/cpuinfo; False where unknown)."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return False
    flags = next((ln.split(":", 1)[1].split() for ln in text.splitlines() if ln.startswith("flags")), [])
    return "amx_bf16" in flags or "avx512_bf16" in flags


def resolve_precision(precision: str, device: str) -> str:
    """'auto' -> 'bfloat16' on a CPU with native bfloat16, else 'float32'; other values unchanged."""
    if precision != "auto":
        return precision
    return "bfloat16" if device == "cpu" and cpu_has_fast_bfloat16() else "float32"


def inference(device: str = "cpu", precision: str = "float32") -> contextlib.ExitStack:
    """Context of a network call: no autograd and, with ``precision`` 'bfloat16', torch autocast (convolutions and
    matrix products in bfloat16, softmax and reductions in float32; cast outputs with ``.float()``)."""
    if precision not in ("float32", "bfloat16"):
        raise ValueError(f"precision {precision!r}: 'float32' or 'bfloat16'")
    stack = contextlib.ExitStack()
    stack.enter_context(torch.inference_mode())
    if precision == "bfloat16":
        stack.enter_context(torch.autocast(device, dtype=torch.bfloat16))
    return stack
