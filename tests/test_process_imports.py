"""What a process loads: reading the registry of process descriptions (every ``sigmaslam`` command does) imports no
heavy library, and the frontend's process (its node module, and its node built as ``sigmaslam frontend`` builds it)
loads none of the back end's loop-closure or occupancy-to-point code (docs/architecture.md)."""

from __future__ import annotations

import json
import subprocess
import sys

from helpers_zenoh import REPO

HEAVY = ("gtsam", "torch", "numba", "cv2", "open3d", "zenoh", "viser", "scipy")


def _modules_after(code: str) -> list[str]:
    out = subprocess.run([sys.executable, "-c", code + "\nimport json, sys\nprint(json.dumps(sorted(sys.modules)))"],
                         cwd=REPO, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def _back_end_code(mods: list[str]) -> list[str]:
    """The back end's loop-closure and o2p modules among ``mods``, their config schemas aside (the system config
    composes every section)."""
    return [m for m in mods if m.startswith(("services.backend.loop", "services.backend.o2p"))
            and not m.endswith((".config", ".loop", ".o2p"))]


def test_reading_the_process_descriptions_imports_no_heavy_library():
    mods = _modules_after("import services.app.processes, services.app.cli")
    assert not [m for m in mods if m.split(".")[0] in HEAVY]


def test_the_frontend_process_loads_no_loop_closure_or_o2p_code():
    assert not _back_end_code(_modules_after("import services.frontend.node"))
    built = _modules_after("from services.app.system_config import load_system_config\n"
                           "from services.frontend.node import DESCRIPTION\n"
                           "from shared.process_description import Start\n"
                           "DESCRIPTION.build(load_system_config(None, []), Start())")
    assert "services.frontend.fast_path" in built and "shared.vio.motion_only" in built
    assert not _back_end_code(built)
