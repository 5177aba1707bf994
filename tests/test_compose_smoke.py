"""tools/compose_smoke's pieces that run without a Docker engine: this machine's pip sources handed to a build."""

from __future__ import annotations

import urllib.error
import urllib.request
from pathlib import Path

import pytest

from tools.compose_smoke.pip_sources import PipSources


def test_local_pip_sources_are_served_on_loopback_and_nothing_else(tmp_path: Path) -> None:
    wheels = tmp_path / "wheels"
    wheels.mkdir()
    (wheels / "demo-1.0-py3-none-any.whl").write_bytes(b"not really a wheel")
    (tmp_path / "secret.txt").write_text("not for the build")
    constraints = tmp_path / "constraints.txt"
    constraints.write_text("torch<=2.14.1\n")
    settings = {"find-links": str(wheels), "extra-index-url": f"file://{tmp_path}/missing https://mirror.example/simple",
                "constraint": str(constraints), "cert": "/etc/ssl/certs/ca-certificates.crt"}
    with PipSources(settings, port=0) as src:
        base = f"http://127.0.0.1:{src.port}"
        assert src.build_args == {"PIP_FIND_LINKS": f"{base}{wheels.resolve()}",
                                  "PIP_EXTRA_INDEX_URL": "https://mirror.example/simple",  # the absent folder dropped
                                  "PIP_CONSTRAINT": f"{base}{constraints.resolve()}"}
        with urllib.request.urlopen(src.build_args["PIP_CONSTRAINT"], timeout=5) as r:
            assert r.read() == b"torch<=2.14.1\n"
        with urllib.request.urlopen(src.build_args["PIP_FIND_LINKS"] + "/", timeout=5) as r:
            assert b"demo-1.0-py3-none-any.whl" in r.read()  # a listing pip's find-links reads
        with pytest.raises(urllib.error.HTTPError) as err:
            urllib.request.urlopen(f"{base}{(tmp_path / 'secret.txt').resolve()}", timeout=5)
        assert err.value.code == 404


def test_remote_sources_pass_unchanged_and_start_no_server() -> None:
    with PipSources({"index-url": "https://pypi.example/simple"}, port=0) as src:
        assert src.build_args == {"PIP_INDEX_URL": "https://pypi.example/simple"} and src._server is None


def test_frames_sent_from_the_players_closing_line() -> None:
    from tools.compose_smoke.outputs import frames_sent

    log = "x INFO transport.node: player: joined\nplayer: 501 frames sent (0 lockstep timeouts)\n"
    assert frames_sent(log) == 501 and frames_sent("player crashed") is None


def test_no_engine_and_no_way_to_start_one_is_a_skip(tmp_path: Path, monkeypatch) -> None:
    """Without a docker client (or dockerd, or root) the smoke test skips, saying why, instead of failing."""
    from tools.compose_smoke import engine, run

    monkeypatch.setattr(engine.shutil, "which", lambda name: None)
    monkeypatch.setattr(run, "compose_command", lambda: ["docker-compose"])
    with pytest.raises(run.Skipped, match="no docker client"):
        run.smoke(tmp_path, timeout_s=1.0, keep_recording=False)
