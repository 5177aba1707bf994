"""The smoke test's steps (the list is in tools/compose_smoke/__main__.py)."""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

from tools.compose_smoke import base_image, outputs
from tools.compose_smoke.engine import Engine, EngineUnavailable
from tools.compose_smoke.pip_sources import PipSources, pip_config
from tools.compose_smoke.stack import Stack, compose_command, containers, logs

REPO = Path(__file__).resolve().parents[2]
IMAGE = "sigmaslam:cpu"
FILES = (REPO / "docker" / "compose.host.yaml",)
SERVICES = ("router", "player", "frontend", "backend", "depth", "mapping", "viewer", "recorder")
ROUTER_PORT, VIEWER_PORT = 7447, 8080  # on the host's loopback (configs/docker-host.yaml)
SERVICE_UID = 10001  # the image's user (docker/Dockerfile)
TORCH_PROBE = "https://download.pytorch.org/whl/cpu/torch/"
STOP_TIMEOUT_S = 150.0  # Ctrl-C to compose's exit: the mapping may take its 60 s grace meshing the map


class Skipped(Exception):
    """No engine can be had here."""


class SmokeFailed(Exception):
    """A check failed (the message says which and what the logs said)."""


def _log(text: str) -> None:
    print(f"[compose-smoke] {text}", flush=True)


def _tail(text: str, lines: int = 25) -> str:
    return "\n".join(text.splitlines()[-lines:])


def _port_busy(port: int) -> bool:
    with socket.socket() as s:
        s.settimeout(1.0)
        return s.connect_ex(("127.0.0.1", port)) == 0


def torch_index() -> str | None:
    """The build's TORCH_INDEX: None keeps the Dockerfile's (PyTorch's CPU index), '' takes pip's own sources where
    that index does not answer; ``$SIGMASLAM_TORCH_INDEX`` wins."""
    if "SIGMASLAM_TORCH_INDEX" in os.environ:
        return os.environ["SIGMASLAM_TORCH_INDEX"]
    try:
        urllib.request.urlopen(urllib.request.Request(TORCH_PROBE, method="HEAD"), timeout=15)
        return None
    except (urllib.error.URLError, OSError):
        _log("the PyTorch CPU index does not answer: torch from pip's own sources (TORCH_INDEX=)")
        return ""


def build_image(log_path: Path) -> dict:
    """``docker build --network host`` of docker/Dockerfile as it is, with this machine's pip sources."""
    with PipSources() as sources:
        args = dict(sources.build_args)
        index = torch_index()
        if index is not None:
            args["TORCH_INDEX"] = index
        cmd = ["docker", "build", "--force-rm", "--network", "host", "-f", "docker/Dockerfile", "-t", IMAGE,
               *(a for k, v in sorted(args.items()) for a in ("--build-arg", f"{k}={v}")), "."]
        _log("building: " + " ".join(cmd))
        t0 = time.monotonic()
        with open(log_path, "w") as log:
            proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                    errors="replace")
            for line in proc.stdout:
                log.write(line)
                if line.startswith(("Step ", "Successfully tagged")):
                    print("  " + line.rstrip()[:150], flush=True)
            rc = proc.wait()
    if rc != 0:
        raise SmokeFailed(f"docker build failed (exit {rc}); {log_path}:\n{_tail(log_path.read_text())}")
    size = subprocess.run(["docker", "image", "inspect", "-f", "{{.Size}}", IMAGE], capture_output=True, text=True)
    return {"build_s": round(time.monotonic() - t0, 1), "image_bytes": int(size.stdout.strip() or 0)}


def default_replica() -> Path:
    """``sigmaslam synth --default`` with this checkout's interpreter: the cached replica's folder."""
    r = subprocess.run([sys.executable, "-m", "services.app.cli", "synth", "--default", "--no-progress"], cwd=REPO,
                       capture_output=True, text=True)
    lines = r.stdout.strip().splitlines()
    if r.returncode != 0 or not lines or not (Path(lines[-1]) / "mav0").is_dir():
        raise SmokeFailed(f"sigmaslam synth --default failed (exit {r.returncode}):\n{_tail(r.stdout + r.stderr)}")
    return Path(lines[-1])


def prepare_folders(work: Path, dataset: Path) -> dict[str, str]:
    """The output folders, made before `up` and given to the services' user; the environment for compose."""
    env = {"SIGMASLAM_DATASET": str(dataset), "SIGMASLAM_OUTPUTS": str(work / "outputs"),
           "SIGMASLAM_RECORDINGS": str(work / "recordings")}
    for key in ("SIGMASLAM_OUTPUTS", "SIGMASLAM_RECORDINGS"):
        shutil.rmtree(env[key], ignore_errors=True)
        Path(env[key]).mkdir(parents=True)
        if os.geteuid() == 0:  # as root: the services run as the image's user and get the folders
            os.chown(env[key], SERVICE_UID, SERVICE_UID)
    if os.geteuid() != 0:  # as anyone else: the services run as you
        env.update(SIGMASLAM_UID=str(os.getuid()), SIGMASLAM_GID=str(os.getgid()))
    if not (REPO.parent / "shared").is_dir():  # compose's default ../../shared: not made beside the checkout
        (work / "shared").mkdir(exist_ok=True)
        env["SIGMASLAM_SHARED"] = str(work / "shared")
    return env


def _viewer_answers() -> bool:
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{VIEWER_PORT}/", timeout=5) as r:
            return r.status == 200
    except (urllib.error.URLError, OSError):
        return False


def watch(stack: Stack, timeout_s: float) -> dict:
    """Until the player has exited 0, the back end has its final trajectory, every service was healthy and the
    viewer answered: the time of each; fails at once on a restart, a crash or compose exiting."""
    t0, last_note = time.monotonic(), 0.0
    healthy: dict[str, float] = {}
    player_done = final_done = viewer_ok = None
    while time.monotonic() - t0 < timeout_s:
        now = time.monotonic() - t0
        cs = containers()
        for name, c in cs.items():
            if c.health == "healthy":
                healthy.setdefault(name, round(now, 1))
            if c.restarts:
                raise SmokeFailed(f"{name} was restarted ({c.restarts}x); its log:\n{_tail(logs(c.id))}")
            if c.status == "exited" and (name != "player" or c.exit_code != 0):
                raise SmokeFailed(f"{name} exited with code {c.exit_code}; its log:\n{_tail(logs(c.id))}")
        if (rc := stack.exited()) is not None:
            raise SmokeFailed(f"compose up ended by itself (exit {rc}):\n{_tail(stack.log_path.read_text())}")
        if player_done is None and cs.get("player") and cs["player"].status == "exited":
            player_done = round(now, 1)
        if viewer_ok is None and "viewer" in healthy and _viewer_answers():
            viewer_ok = round(now, 1)
        if player_done is not None and final_done is None and "final trajectory in" in logs(cs["backend"].id):
            final_done = round(now, 1)
        if None not in (player_done, final_done, viewer_ok) and set(healthy) >= set(SERVICES):
            return {"healthy_s": healthy, "all_healthy_s": max(healthy.values()), "player_exit_s": player_done,
                    "final_trajectory_s": final_done, "viewer_200_s": viewer_ok}
        if now - last_note >= 15:
            last_note = now
            _log(f"{now:.0f} s: healthy {', '.join(sorted(healthy)) or '-'}; "
                 + ", ".join(f"{n} {c.status}" for n, c in sorted(cs.items()) if n not in healthy))
        time.sleep(1.0)
    missing = sorted(set(SERVICES) - set(healthy))
    raise SmokeFailed(f"not done within {timeout_s:.0f} s: never healthy {missing or '-'}, player done "
                      f"{player_done}, final trajectory {final_done}, viewer 200 {viewer_ok}")


def stop(stack: Stack) -> dict:
    """Ctrl-C: compose must stop every container and exit 0; no container restarted, each one's exit code."""
    t0 = time.monotonic()
    rc = stack.interrupt(STOP_TIMEOUT_S)
    stop_s = round(time.monotonic() - t0, 1)
    cs = containers()
    exits = {n: c.exit_code for n, c in sorted(cs.items())}
    problems = []
    if rc != 0:
        problems.append(f"compose up exited {rc} after Ctrl-C (None: still running after {STOP_TIMEOUT_S:.0f} s)")
    problems += [f"{n} still {c.status}" for n, c in cs.items() if c.status != "exited"]
    problems += [f"{n} exited {c.exit_code}" for n, c in cs.items() if c.exit_code != 0]
    problems += [f"{n} restarted {c.restarts}x" for n, c in cs.items() if c.restarts]
    if problems:
        raise SmokeFailed("after Ctrl-C: " + "; ".join(problems) + f"\n{_tail(stack.log_path.read_text())}")
    return {"compose_exit_code": rc, "stop_s": stop_s, "exit_codes": exits,
            "restarts": {n: c.restarts for n, c in sorted(cs.items())}}


def run_stack(compose: list[str], env: dict[str, str], work: Path, timeout_s: float) -> dict:
    for port in (ROUTER_PORT, VIEWER_PORT):
        if _port_busy(port):
            raise SmokeFailed(f"127.0.0.1:{port} is taken (a `sigmaslam up` or demo running?): the stack needs it")
    stack = Stack(compose, list(FILES), env, REPO, work / "logs" / "compose-up.log")
    stack.down()  # what an interrupted earlier run left
    t0 = time.monotonic()
    try:
        _log(f"up: {' '.join(stack.base)} up --no-build (log {stack.log_path})")
        stack.up()
        figures = watch(stack, timeout_s)
        time.sleep(2.0)  # the recorder closes a chunk every second: the final trajectory is on disk
        figures.update(stop(stack))
        figures["up_to_stopped_s"] = round(time.monotonic() - t0, 1)
        return figures
    finally:
        for name, c in containers().items():
            (work / "logs" / f"{name}.log").write_text(logs(c.id))
        stack.down()


def smoke(work: Path, timeout_s: float, keep_recording: bool) -> dict:
    compose = compose_command()
    if compose is None:
        raise Skipped("neither `docker compose` nor `docker-compose` is installed (Debian: docker-compose)")
    (work / "logs").mkdir(parents=True, exist_ok=True)
    summary: dict = {"compose": " ".join(compose)}
    t0 = time.monotonic()
    engine = Engine(work / "logs" / "dockerd.log")
    try:
        engine.start()
    except EngineUnavailable as exc:
        raise Skipped(f"no Docker engine: {exc}") from exc
    try:
        summary["engine"] = "started here" if engine.started else "already running"
        summary["engine_s"] = round(time.monotonic() - t0, 1)
        t = time.monotonic()
        try:
            summary["base_image"] = base_image.ensure_base(cert=pip_config().get("cert"))
        except base_image.BaseImageError as exc:
            raise SmokeFailed(str(exc)) from exc
        summary["base_image_s"] = round(time.monotonic() - t, 1)
        summary.update(build_image(work / "logs" / "build.log"))
        t = time.monotonic()
        dataset = default_replica()
        summary["replica_s"] = round(time.monotonic() - t, 1)
        env = prepare_folders(work, dataset)
        summary.update(run_stack(compose, env, work, timeout_s))
        problems, figures = outputs.check(Path(env["SIGMASLAM_OUTPUTS"]), Path(env["SIGMASLAM_RECORDINGS"]))
        figures["frames_sent"] = outputs.frames_sent((work / "logs" / "player.log").read_text())
        summary.update(figures)
        if not keep_recording and figures.get("recording"):
            Path(figures["recording"]).unlink()
        if problems:
            raise SmokeFailed("; ".join(problems))
        summary["passed"] = True
        return summary
    except SmokeFailed as exc:
        summary["failed"] = str(exc).splitlines()[0]
        raise
    finally:
        summary["total_s"] = round(time.monotonic() - t0, 1)
        (work / "summary.json").write_text(json.dumps(summary, indent=1))
        if engine.started:
            _log("stopping the engine started for the test")
        engine.stop()
