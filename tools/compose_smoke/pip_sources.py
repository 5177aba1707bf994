"""This machine's pip package sources, handed to a container build.

pip here may be configured with package sources that are folders on this machine: wheel folders (``find-links``),
``file://`` indexes, a constraints file. A build container cannot see them. :class:`PipSources` starts a small HTTP
server on 127.0.0.1 that serves exactly those files (an index with the folder it sits in: its pages link to files
beside it; nothing else on the machine) and gives the build args that point pip inside the build at them:
``PIP_INDEX_URL``, ``PIP_EXTRA_INDEX_URL``, ``PIP_FIND_LINKS``, ``PIP_CONSTRAINT``, ``PIP_TRUSTED_HOST``, which
docker/Dockerfile declares (empty by default, so a normal build uses pip's defaults).
Remote sources are passed on as they are. The build must run with ``--network host`` to reach the server.

The port is fixed (:data:`DEFAULT_PORT`, or ``$SIGMASLAM_SMOKE_PIP_PORT``) so that the build args, and with them
docker's layer cache, are the same from one run to the next. TLS trust is not a build arg: the stand-in base image
carries this machine's CA bundle (tools/compose_smoke/base_image.py).
"""

from __future__ import annotations

import functools
import http.server
import os
import re
import subprocess
import sys
import threading
from pathlib import Path
from urllib.parse import unquote, urlparse

DEFAULT_PORT = 8790
# pip setting -> the environment variable (= docker/Dockerfile build arg) that carries it
SETTINGS = {"index-url": "PIP_INDEX_URL", "extra-index-url": "PIP_EXTRA_INDEX_URL", "find-links": "PIP_FIND_LINKS",
            "constraint": "PIP_CONSTRAINT", "trusted-host": "PIP_TRUSTED_HOST"}
INDEXES = ("index-url", "extra-index-url")
_LINE = re.compile(r"^(?P<scope>[^.]*)\.(?P<key>[\w-]+)='(?P<value>.*)'$")


def pip_config(python: str = sys.executable) -> dict[str, str]:
    """The settings of ``pip config list`` (all files, then the environment, which wins), without the scopes."""
    out = subprocess.run([python, "-m", "pip", "config", "list"], capture_output=True, text=True, timeout=60)
    ranked: list[tuple[int, str, str]] = []
    for line in out.stdout.splitlines():
        m = _LINE.match(line.strip())
        if m:  # ':env:' settings override the files' ones, as pip applies them
            ranked.append((m["scope"] == ":env:", m["key"], m["value"]))
    return {key: value for _, key, value in sorted(ranked, key=lambda r: r[0])}


def _local_path(item: str) -> Path | None:
    """The folder or file on this machine that a pip source names, or None for a remote one."""
    if item.startswith("file:"):
        return Path(unquote(urlparse(item).path))
    if item.startswith("/"):
        return Path(item)
    return None


class _Handler(http.server.SimpleHTTPRequestHandler):
    """Serves files under the allowed paths only; everything else is 404."""

    def __init__(self, *args, allowed: tuple[Path, ...], **kwargs):
        self.allowed = allowed
        super().__init__(*args, directory="/", **kwargs)

    def translate_path(self, path: str) -> str:
        local = Path(super().translate_path(path)).resolve()
        if any(local == a or a in local.parents for a in self.allowed):
            return str(local)
        return "/nonexistent-sigmaslam-smoke"

    def log_message(self, format: str, *args) -> None:  # pip's requests are not worth a line each
        pass


class PipSources:
    """``with PipSources() as s: s.build_args``: this machine's pip sources, those on disk served on 127.0.0.1."""

    def __init__(self, settings: dict[str, str] | None = None, port: int | None = None):
        self.settings = pip_config() if settings is None else settings
        self.port = int(os.environ.get("SIGMASLAM_SMOKE_PIP_PORT", DEFAULT_PORT)) if port is None else port
        self.build_args: dict[str, str] = {}
        self.served: list[Path] = []
        self._server: http.server.ThreadingHTTPServer | None = None

    def _translate(self, value: str) -> str:
        items = []
        for item in value.split():
            path = _local_path(item)
            if path is None:
                items.append(item)
            elif path.exists():
                items.append(f"http://127.0.0.1:{self.port}{path.resolve()}")
            else:
                print(f"[compose-smoke] pip source {item} is configured here but absent; not passed to the build",
                      flush=True)
        return " ".join(items)

    def __enter__(self) -> PipSources:
        used = {key: self.settings[key] for key in SETTINGS if self.settings.get(key)}
        for key, value in used.items():
            for path in filter(None, map(_local_path, value.split())):
                if path.exists():  # an index's pages link to its files beside it (simple/x/ -> ../../files/)
                    self.served.append(path.resolve().parent if key in INDEXES else path.resolve())
        if self.served:
            handler = functools.partial(_Handler, allowed=tuple(self.served))
            try:
                self._server = http.server.ThreadingHTTPServer(("127.0.0.1", self.port), handler)
            except OSError as exc:
                raise RuntimeError(f"cannot serve this machine's pip sources on 127.0.0.1:{self.port} ({exc}); "
                                   "set SIGMASLAM_SMOKE_PIP_PORT to a free port") from exc
            self.port = self._server.server_address[1]
            threading.Thread(target=self._server.serve_forever, name="pip-sources", daemon=True).start()
        for key, value in used.items():
            if translated := self._translate(value):
                self.build_args[SETTINGS[key]] = translated
        return self

    def __exit__(self, *exc) -> None:
        if self._server is not None:
            self._server.shutdown()
            self._server.server_close()
