"""tools/zenoh_client_example.py (plain zenoh-python in client mode + shared.codec) receives poses and
meshes from a separate publisher process through a real router."""

from __future__ import annotations

import subprocess
import sys

from helpers_zenoh import REPO, child_env, router
from services.app.system_config import SystemConfig
from shared.config import to_yaml


def test_client_example_prints_poses_and_meshes(tmp_path):
    with router() as tcfg:
        path = tmp_path / "config.yaml"
        path.write_text(to_yaml(SystemConfig(transport=tcfg)))
        client = subprocess.Popen([sys.executable, "-m", "tools.zenoh_client_example", "--connect", tcfg.connect[0],
                                   "--namespace", tcfg.namespace, "--pose-every", "5", "--count", "12"],
                                  cwd=REPO, env=child_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        pub = subprocess.Popen([sys.executable, "-m", "tools.viewer_demo_publisher", str(path), "--duration", "20",
                                "--reloc-period", "1"], cwd=REPO, env=child_env(), stdout=subprocess.PIPE,
                               stderr=subprocess.STDOUT, text=True)
        try:
            out, err = client.communicate(timeout=40)
        finally:
            pub.terminate()
            pub.wait(10)
    lines = out.splitlines()
    assert client.returncode == 0 and len(lines) == 12, (out, err)
    poses = [ln for ln in lines if ln.startswith("pose ")]
    meshes = [ln for ln in lines if ln.startswith("submap ")]
    assert poses and meshes, out
    # the demo body flies at z = 1 m; its submaps are spheres (642 vertices) and boxes (8)
    assert all("p_W=[" in ln and ln.split("p_W=[")[1].split("]")[0].split()[2] == "1.000" for ln in poses)
    assert all(("642 vertices, 1280 faces" in ln) or ("8 vertices, 12 faces" in ln) for ln in meshes), meshes
    assert "skipped" not in err
