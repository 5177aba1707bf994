"""A stand-in for the base image that docker/Dockerfile names, built from Debian packages where none can be pulled.

``python:3.11-slim-bookworm`` is Debian bookworm with Python 3.11 whose ``python`` and ``pip`` come first on PATH and
install system-wide. Where no container registry answers, :func:`ensure_base` builds a stand-in with the same name:

- a minimal bookworm root file system from ``debootstrap`` (Debian's package sources, as this machine's apt reaches
  them) with Debian's python3.11, python3.11-venv (with python3-venv: it needs python3 to configure),
  ca-certificates, netbase and tzdata;
- a venv in /usr/local/python first on PATH (Debian's own Python refuses system-wide ``pip install``), so that the
  Dockerfile's ``pip install`` and ``python`` work unmodified; LANG=C.UTF-8, CMD python3, as the official image;
- this machine's TLS trust: the CA bundle that pip here is configured with (``pip config``'s ``cert``) becomes the
  image's system bundle and pip's ``cert`` in /etc/pip.conf, so pip in the build trusts what pip here trusts;
- apt's package sources from this machine's /etc/apt (else deb.debian.org).

The Dockerfile is not changed for it. Needs root and ``debootstrap`` (installed with apt-get when missing); about
2-3 minutes once, then the image stays in the engine's cache.
"""

from __future__ import annotations

import shutil
import subprocess
import tempfile
from pathlib import Path

NAME = "python:3.11-slim-bookworm"
PACKAGES = ("python3.11", "python3.11-venv", "python3-venv", "ca-certificates", "netbase", "tzdata")
VENV = "/usr/local/python"
DEFAULT_MIRROR = "http://deb.debian.org/debian"
SYSTEM_BUNDLE = "/etc/ssl/certs/ca-certificates.crt"
CHANGES = (f"ENV PATH={VENV}/bin:/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin",
           "ENV LANG=C.UTF-8", 'CMD ["python3"]')


class BaseImageError(RuntimeError):
    """The base image can neither be pulled nor built here."""


def _log(text: str) -> None:
    print(f"[compose-smoke] {text}", flush=True)


def present(name: str = NAME) -> bool:
    return subprocess.run(["docker", "image", "inspect", name], capture_output=True).returncode == 0


def pull(name: str = NAME, timeout_s: float = 120.0) -> bool:
    """Whether ``docker pull`` got the image (False when no registry answers in time)."""
    try:
        return subprocess.run(["docker", "pull", "-q", name], capture_output=True, timeout=timeout_s).returncode == 0
    except subprocess.TimeoutExpired:
        return False


def _apt_mirror() -> str:
    """The first Debian archive this machine's apt uses (deb822 or one-line sources), else deb.debian.org."""
    files = sorted(Path("/etc/apt/sources.list.d").glob("*.sources")) + [Path("/etc/apt/sources.list")]
    for f in files:
        text = f.read_text(errors="replace") if f.is_file() else ""
        for line in text.splitlines():
            words = line.split()
            if words[:1] == ["URIs:"] and len(words) > 1 and "security" not in words[1]:
                return words[1]
            if words[:1] == ["deb"] and len(words) > 2 and "security" not in line:
                return next(w for w in words[1:] if "://" in w)
    return DEFAULT_MIRROR


def _copy_apt_sources(root: Path) -> None:
    """This machine's apt sources (the archive, updates, security) instead of debootstrap's one line."""
    host = sorted(Path("/etc/apt/sources.list.d").glob("*.sources"))
    if not host:
        return
    (root / "etc/apt/sources.list").write_text("")
    for f in host:
        shutil.copy(f, root / "etc/apt/sources.list.d" / f.name)


def _trust(root: Path, cert: str | None) -> None:
    """Make the CA bundle pip here trusts the image's system bundle and pip's ``cert``."""
    bundle = Path(cert) if cert else Path(SYSTEM_BUNDLE)
    if not bundle.is_file():
        return
    shutil.copy(bundle, root / SYSTEM_BUNDLE.lstrip("/"))
    (root / "etc/pip.conf").write_text(f"[global]\ncert = {SYSTEM_BUNDLE}\n")


def _debootstrap() -> str:
    exe = shutil.which("debootstrap") or ("/usr/sbin/debootstrap" if Path("/usr/sbin/debootstrap").exists() else None)
    if exe:
        return exe
    if shutil.which("apt-get") is None:
        raise BaseImageError("debootstrap is not installed and there is no apt-get to install it")
    _log("installing debootstrap (apt-get)")
    if subprocess.run(["apt-get", "install", "-y", "-q", "debootstrap"], capture_output=True).returncode != 0:
        subprocess.run(["apt-get", "update", "-q"], capture_output=True)
        r = subprocess.run(["apt-get", "install", "-y", "-q", "debootstrap"], capture_output=True, text=True)
        if r.returncode != 0:
            raise BaseImageError(f"apt-get install debootstrap failed:\n{r.stderr[-2000:]}")
    return shutil.which("debootstrap") or "/usr/sbin/debootstrap"


def build(name: str = NAME, cert: str | None = None, work: Path | None = None) -> None:
    """Build the stand-in and tag it ``name`` (see the module's docstring)."""
    exe = _debootstrap()
    with tempfile.TemporaryDirectory(prefix="sigmaslam-base-", dir=work) as tmp:
        root = Path(tmp) / "rootfs"
        mirror = _apt_mirror()
        _log(f"building a stand-in for {name}: debootstrap bookworm from {mirror} (2-3 min)")
        r = subprocess.run([exe, "--variant=minbase", f"--include={','.join(PACKAGES)}", "bookworm", str(root),
                            mirror], capture_output=True, text=True)
        if r.returncode != 0:
            raise BaseImageError(f"debootstrap failed (exit {r.returncode}):\n{(r.stdout + r.stderr)[-3000:]}")
        r = subprocess.run(["chroot", str(root), "python3.11", "-m", "venv", VENV], capture_output=True, text=True)
        if r.returncode != 0:
            raise BaseImageError(f"python3.11 -m venv {VENV} failed in the new root:\n{r.stderr[-2000:]}")
        _copy_apt_sources(root)
        _trust(root, cert)
        for junk in ("var/cache/apt/archives", "var/lib/apt/lists"):
            for f in (root / junk).glob("*"):
                if f.is_file():
                    f.unlink()
        tar = subprocess.Popen(["tar", "-C", str(root), "--exclude=./dev/*", "--exclude=./proc/*",
                                "--exclude=./sys/*", "-c", "."], stdout=subprocess.PIPE)
        changes = [a for c in CHANGES for a in ("--change", c)]
        r = subprocess.run(["docker", "import", *changes, "-", name], stdin=tar.stdout, capture_output=True, text=True)
        tar.stdout.close()
        if tar.wait() != 0 or r.returncode != 0:
            raise BaseImageError(f"docker import failed: {r.stderr.strip()}")
    _log(f"stand-in {name} built (Debian bookworm, Python 3.11 in {VENV})")


def ensure_base(name: str = NAME, cert: str | None = None) -> str:
    """Make sure ``name`` is in the engine: 'cached', 'pulled' or 'built' (the stand-in)."""
    if present(name):
        return "cached"
    _log(f"pulling {name}")
    if pull(name):
        return "pulled"
    _log(f"{name} cannot be pulled (no registry answers)")
    build(name, cert)
    return "built"
