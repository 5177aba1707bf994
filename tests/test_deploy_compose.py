"""docker/compose.yaml: valid for docker-compose, every command a real sigmaslam CLI command, viewer on localhost.

The compose files are validated with Debian's ``docker-compose config`` (no Docker engine needed);
the command checks parse each command with the subcommand's own argument parser. The stack itself runs in
``python -m tools.compose_smoke`` (.ci/run; a Docker engine needed).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import shutil
import subprocess
from pathlib import Path

import pytest
import yaml

from services.app.cli import command_names, command_parser
from services.app.system_config import load_system_config
from tests.helpers_zenoh import REPO

COMPOSE = REPO / "docker" / "compose.yaml"
GPU = REPO / "docker" / "compose.gpu.yaml"
HOST = REPO / "docker" / "compose.host.yaml"
PIPELINE = ("router", "player", "frontend", "backend", "depth", "mapping", "viewer", "recorder", "ros2")


def _resolved(*files: Path) -> dict:
    """The compose model after docker-compose's own merging and interpolation, or the raw YAML if absent."""
    exe = shutil.which("docker-compose")
    if exe is None:
        pytest.skip("docker-compose is not installed (Debian package docker-compose; `make system-deps`)")
    args = [exe]
    for f in files:
        args += ["-f", str(f)]
    r = subprocess.run([*args, "config"], capture_output=True, text=True, cwd=REPO,
                       env={k: v for k, v in os.environ.items() if not k.startswith("SIGMASLAM_")})
    assert r.returncode == 0, f"docker-compose config failed:\n{r.stderr}"
    return yaml.safe_load(r.stdout)


@pytest.fixture(scope="module")
def compose() -> dict:
    return _resolved(COMPOSE)


@pytest.fixture(scope="module")
def host_compose() -> dict:
    return _resolved(HOST)


def _argv(command: object) -> list[str]:
    return shlex.split(command) if isinstance(command, str) else list(command)


def _commands(model: dict) -> list[tuple[str, list[str]]]:
    out = []
    for name, svc in model["services"].items():
        out.append((name, _argv(svc["command"])))
        test = svc.get("healthcheck", {}).get("test")
        if test:
            test = _argv(test)
            assert test[0] in ("CMD", "CMD-SHELL"), (name, test)
            out.append((f"{name} healthcheck", test[1:] if test[0] == "CMD" else shlex.split(test[1])))
    return out


def _parse(argv: list[str]) -> argparse.Namespace:
    """Parse ``sigmaslam ...`` argv with the subcommand's own parser (as services.app.cli does)."""
    assert argv[0] == "sigmaslam", f"not a sigmaslam command: {argv}"
    assert argv[1] in command_names(), f"{argv[1]!r} is not a sigmaslam subcommand ({', '.join(command_names())})"
    return command_parser(argv[1], exit_on_error=False).parse_args(argv[2:])


def test_compose_validates_with_gpu_override() -> None:
    model = _resolved(COMPOSE, GPU)
    depth = model["services"]["depth"]
    assert "Dockerfile.cuda" in depth["build"]["dockerfile"]
    assert depth["deploy"]["resources"]["reservations"]["devices"][0]["capabilities"] == ["gpu"]
    assert _parse(_argv(depth["command"])).set == ["depth.device=cuda"]


def test_one_service_per_process(compose: dict) -> None:
    assert sorted(compose["services"]) == sorted(PIPELINE)
    # the ROS 2 face is off unless asked for (`--profile ros2`); everything else starts with a plain `up`
    assert [n for n, svc in compose["services"].items() if svc.get("profiles")] == ["ros2"]
    assert compose["services"]["ros2"]["profiles"] == ["ros2"]
    for name, svc in compose["services"].items():
        assert svc.get("restart") in ("unless-stopped", "on-failure", "always"), name
        assert "healthcheck" in svc, name
        if name != "router":
            assert svc["depends_on"]["router"]["condition"] == "service_healthy", name


@pytest.mark.parametrize("variant", ["bridge", "host"])
def test_every_command_is_a_sigmaslam_cli_command(variant: str, compose: dict, host_compose: dict) -> None:
    for name, argv in _commands(compose if variant == "bridge" else host_compose):
        args = _parse(argv)
        config = getattr(args, "config", None) or next((a for a in argv if a.endswith(".yaml")), None)
        assert config is not None, f"{name}: no config file in {argv}"
        assert (REPO / config).is_file(), f"{name}: {config} is not in the repository (the image's /app)"
        load_system_config(REPO / config)  # unknown keys would raise


def test_healthchecks_ask_for_their_own_service(compose: dict) -> None:
    for name, svc in compose["services"].items():
        test = _argv(svc["healthcheck"]["test"])
        assert test[1:4] == ["sigmaslam", "health", name], (name, test)


def test_only_the_viewer_publishes_a_port_and_only_on_localhost(compose: dict) -> None:
    for name, svc in compose["services"].items():
        ports = svc.get("ports", [])
        if name != "viewer":
            assert not ports, f"{name} publishes {ports}"
            continue
        assert ports, "the viewer page is not published"
        for port in ports:
            host_ip = port.get("host_ip") if isinstance(port, dict) else str(port).split(":")[0]
            assert host_ip == "127.0.0.1", f"viewer published on {port}"
    cfg = load_system_config(REPO / "configs" / "docker.yaml")
    target = compose["services"]["viewer"]["ports"][0]
    assert str(cfg.viewer.port) in str(target)


def test_docker_config_reaches_the_router_by_name() -> None:
    cfg = load_system_config(REPO / "configs" / "docker.yaml").transport
    assert cfg.mode == "client" and cfg.connect == ("tcp/router:7447",)
    assert not cfg.shared_memory


def test_volumes_for_datasets_outputs_and_recordings(compose: dict) -> None:
    def targets(svc: dict) -> set[str]:
        return {(v["target"] if isinstance(v, dict) else v.split(":")[1]) for v in svc.get("volumes", [])}

    assert "/data/dataset" in targets(compose["services"]["player"])
    assert "/recordings" in targets(compose["services"]["recorder"])
    assert "/outputs" in targets(compose["services"]["mapping"])
    cfg = load_system_config(REPO / "configs" / "docker.yaml")
    assert cfg.recorder.output_dir == "/recordings" and cfg.mapping.output_dir.startswith("/outputs")


def test_dockerfiles_install_torch_then_the_project() -> None:
    cpu = (REPO / "docker" / "Dockerfile").read_text()
    cuda = (REPO / "docker" / "Dockerfile.cuda").read_text()
    assert "FROM python:3.11-slim-bookworm" in cpu and "libusb-1.0-0" in cpu and "libegl1" in cpu
    assert "ARG TORCH_INDEX=https://download.pytorch.org/whl/cpu" in cpu
    assert "whl/cu" in cuda
    for text in (cpu, cuda):
        assert text.index("torch==") < text.index("COPY services"), "torch must come before the project"
    # what the images copy is what the project is made of
    for folder in ("services", "shared", "transport", "tools", "configs", "data/euroc"):
        assert f"COPY {folder} {folder}" in cpu and f"COPY {folder} {folder}" in cuda
    ignored = (REPO / ".dockerignore").read_text().split()
    assert "data/*" in ignored and "!data/euroc" in ignored  # generated data stays out, the bundled files go in


def test_player_waits_for_everything_that_takes_its_data(compose: dict) -> None:
    takers = {"frontend", "backend", "depth", "mapping", "recorder"}
    player = compose["services"]["player"]
    assert {n for n, d in player["depends_on"].items() if d["condition"] == "service_healthy"} >= takers | {"router"}
    assert set(_parse(_argv(player["command"])).wait_for.split(",")) >= takers


def test_services_run_as_the_invoking_user_or_the_images(compose: dict) -> None:
    """Debian's docker-compose resolves the default (the image's user); SIGMASLAM_UID/GID give another."""
    for name, svc in compose["services"].items():
        assert svc["user"] == "10001:10001", name
    raw = yaml.safe_load(COMPOSE.read_text())
    assert raw["x-sigmaslam"]["user"] == "${SIGMASLAM_UID:-10001}:${SIGMASLAM_GID:-10001}"


def test_host_variant_is_the_same_stack_on_loopback(compose: dict, host_compose: dict) -> None:
    """compose.host.yaml is compose.yaml with host networking, configs/docker-host.yaml and no published port."""
    assert sorted(host_compose["services"]) == sorted(compose["services"])
    for name, svc in host_compose["services"].items():
        assert svc.pop("network_mode") == "host" and svc.pop("ipc") == "host", name
        assert svc["build"].pop("network") == "host", name
        assert "ports" not in svc, name
        same = json.loads(json.dumps(svc).replace("configs/docker-host.yaml", "configs/docker.yaml"))
        base = {k: v for k, v in compose["services"][name].items() if k != "ports"}
        assert same == base, name
    cfg = load_system_config(REPO / "configs" / "docker-host.yaml")
    assert cfg.viewer.host == "127.0.0.1"
    for endpoint in (*cfg.transport.connect, *cfg.transport.listen, *cfg.transport.router_listen):
        assert endpoint.startswith("tcp/127.0.0.1:"), endpoint


def test_image_runs_as_an_unprivileged_user_with_writable_caches() -> None:
    for name in ("Dockerfile", "Dockerfile.cuda"):
        text = (REPO / "docker" / name).read_text()
        assert "USER sigmaslam" in text and "--uid 10001" in text, name
        assert "NUMBA_CACHE_DIR=/tmp/" in text and "HOME=/tmp" in text, name  # numba's cache=True, any uid
        assert 'ENTRYPOINT ["sigmaslam-entrypoint"]' in text, name
        for arg in ("PIP_INDEX_URL", "PIP_EXTRA_INDEX_URL", "PIP_FIND_LINKS", "PIP_CONSTRAINT"):
            assert f"ARG {arg}\n" in text, (name, arg)  # no default: pip's own unless given
        assert '${TORCH_INDEX:+--index-url "${TORCH_INDEX}"}' in text, name


def test_entrypoint_runs_the_command_when_the_folders_are_writable(tmp_path: Path) -> None:
    r = subprocess.run(["sh", str(REPO / "docker" / "entrypoint.sh"), "sh", "-c", "exit 7"],
                       env={**os.environ, "SIGMASLAM_WRITABLE": str(tmp_path)}, capture_output=True, text=True)
    assert r.returncode == 7, r.stderr
