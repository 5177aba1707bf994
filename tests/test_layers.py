"""Layers that hold (issue 20.2): every import between the project's packages goes downwards.

    shared  <-  transport  <-  config schemas  <-  process packages  <-  application  <-  tools

- ``shared/``: code two or more processes use (messages, codec, geometry, cameras, the VIO core, the occupancy field,
  ATE).
- ``transport/``: Zenoh session, publishers/subscribers, queues, the service shell, the node runner.
- config schemas: the config modules of the process packages (``services/<process>/**/config.py``,
  ``*_config.py``); a schema imports only shared, transport and other schemas.
- process packages: ``services/<process>/`` (one per OS process, each describing itself in its ``node.py``). A
  process package never imports another process package, nor the application: it gets the system config handed
  over (its own section and those it shares, e.g. the frontend reads ``backend``, the VIO config it shares).
- application: ``services/app/`` (the CLI, commands, supervisor, the system config, the process registry, what
  only commands use).
- ``tools/``: developer scripts; nothing in the product imports them.

Every ``import`` counts, also those inside functions (lazy) or under ``TYPE_CHECKING``, and so does a string
that names one of the project's modules (``importlib.import_module(name)``, ``python -m name``, the CLI's
command registries). There are no exceptions: the developer commands are ``python -m tools ...``.

A ``shared/`` module serves two processes or more (a process package, or the application, which runs processes of
its own: ``sigmaslam run``, ``up``, the router); one that serves fewer belongs to its user.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = next(p for p in Path(__file__).resolve().parents if (p / "pyproject.toml").exists())  # wherever tests/ nests it
PACKAGES = ("shared", "transport", "services", "tools")
LAYERS = ("shared", "transport", "config schema", "process package", "application", "tools")
APP = "app"

_MODULE_NAME = re.compile(r"^(%s)(\.\w+)+$" % "|".join(PACKAGES))


def module_of(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def all_modules() -> dict[str, Path]:
    return {module_of(p): p for pkg in PACKAGES for p in sorted((ROOT / pkg).rglob("*.py"))}


def layer(module: str) -> int | None:
    """Index in :data:`LAYERS` of a project module (None: not one of the project's packages)."""
    parts = module.split(".")
    if parts[0] not in PACKAGES:
        return None
    if parts[0] != "services":
        return {"shared": 0, "transport": 1, "tools": 5}[parts[0]]
    if len(parts) == 1:
        return None  # the bare namespace 'services' holds nothing
    if parts[1] == APP:
        return 4
    if len(parts) > 2 and (parts[-1] == "config" or parts[-1].endswith("_config")):
        return 2
    return 3


def package(module: str) -> str | None:
    """The services/ package a module belongs to ('backend', 'app', ...; None outside one)."""
    parts = module.split(".")
    return parts[1] if parts[0] == "services" and len(parts) > 2 else None


def imports_of(source: str, module: str, is_package: bool, modules: set[str]) -> list[tuple[int, str, str, bool]]:
    """(line, project module, statement, named as a string) for every reference to a project module."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found += [(node.lineno, a.name, ast.unparse(node), False) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".")[: len(module.split(".")) - node.level + (1 if is_package else 0)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            for a in node.names:  # 'from pkg import mod' imports pkg.mod
                sub = f"{target}.{a.name}"
                found.append((node.lineno, sub if sub in modules else target, ast.unparse(node), False))
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) and _MODULE_NAME.match(node.value):
            if node.value in modules:
                found.append((node.lineno, node.value, repr(node.value), True))
    return [f for f in found if layer(f[1]) is not None]


def violations(rel_path: str, source: str, modules: set[str]) -> list[str]:
    """What the layering rule forbids in one file, one message per reference: 'file:line: statement: why'."""
    module = module_of(ROOT / rel_path)
    src_layer, src_pkg = layer(module), package(module)
    is_process = src_layer is not None and src_pkg is not None and src_pkg != APP
    out = []
    for line, target, text, by_name in imports_of(source, module, rel_path.endswith("__init__.py"), modules):
        dst_layer, dst_pkg = layer(target), package(target)
        why = None
        if dst_layer > src_layer:
            why = f"{LAYERS[src_layer]} {module} may not import {LAYERS[dst_layer]} {target}"
        elif is_process and dst_pkg is not None and dst_pkg != src_pkg:
            what = "the application" if dst_pkg == APP else f"process package services/{dst_pkg}"
            why = f"process package services/{src_pkg} may not import {what} ({target})"
        if why:
            out.append(f"{rel_path}:{line}: {text}{' (names a module)' if by_name else ''}: {why}")
    return out


def test_every_import_goes_down_the_layers():
    mods = all_modules()
    names = set(mods)
    bad = []
    for module, path in mods.items():
        bad += violations(str(path.relative_to(ROOT)), path.read_text(encoding="utf-8"), names)
    assert not bad, "imports against the layering (see tests/test_layers.py):\n" + "\n".join(bad)


def test_services_holds_process_packages_and_the_application():
    """services/ = one package per process (each describing itself in its node.py) and the application."""
    services = ROOT / "services"
    loose = sorted(p.name for p in services.glob("*.py") if p.name != "__init__.py")
    assert not loose, f"modules directly in services/ (belong in services/app/ or a process package): {loose}"
    for d in sorted(p for p in services.iterdir() if (p / "__init__.py").exists()):
        if d.name != APP:
            node = d / "node.py"
            assert node.exists() and "\nDESCRIPTION = ProcessDescription(" in node.read_text(), (
                f"services/{d.name}/ is not a process (no node.py ending in a DESCRIPTION): move it")


def _closure(deps: dict[str, set[str]], start: list[str]) -> set[str]:
    seen, todo = set(), list(start)
    while todo:
        m = todo.pop()
        if m not in seen:
            seen.add(m)
            todo += deps.get(m, ())
    return seen


def users_of_shared() -> dict[str, set[str]]:
    """shared module -> the process packages and the application whose code imports it (directly or through other
    modules)."""
    mods = all_modules()
    names = set(mods)
    deps = {m: {t for _, t, _, _ in imports_of(p.read_text(encoding="utf-8"), m, p.name == "__init__.py", names)
                if t in names} for m, p in mods.items()}
    users: dict[str, set[str]] = {m: set() for m in mods if m.split(".")[0] == "shared"}
    for pkg in {package(m) for m in mods} - {None}:
        for m in _closure(deps, [m for m in mods if package(m) == pkg]):
            if m in users:
                users[m].add(pkg)
    return users


def test_every_shared_module_serves_two_processes():
    """shared/ holds what two processes or more use; a module one user needs lives with it."""
    lonely = {m: sorted(u) for m, u in users_of_shared().items()
              if len(u) < 2 and not (ROOT / m.replace(".", "/") / "__init__.py").exists()}
    assert not lonely, f"shared modules that serve fewer than two processes (move them to their user): {lonely}"


def test_the_check_sees_lazy_imports_strings_and_names_file_and_line():
    names = set(all_modules())
    src = ("import numpy as np\n"
           "from shared.geometry import inv_T\n"
           "from services.app.system_config import load_system_config\n"
           "def f():\n"
           "    from services.mapping.submaps import Submap\n"
           "    from services.app import supervisor\n"
           "    return importlib.import_module('tools.eval.diagnose')\n")
    bad = violations("services/backend/x.py", src, names)
    assert len(bad) == 4, bad
    assert bad[0] == ("services/backend/x.py:3: from services.app.system_config import load_system_config: process "
                      "package services.backend.x may not import application services.app.system_config")
    assert bad[1] == ("services/backend/x.py:5: from services.mapping.submaps import Submap: process package "
                      "services/backend may not import process package services/mapping (services.mapping.submaps)")
    assert bad[2] == ("services/backend/x.py:6: from services.app import supervisor: process package "
                      "services.backend.x may not import application services.app.supervisor")
    assert bad[3].startswith("services/backend/x.py:7: 'tools.eval.diagnose' (names a module): ")
    assert violations("shared/x.py", "from transport.queues import Empty\n", names) == [
        "shared/x.py:1: from transport.queues import Empty: shared shared.x may not import transport transport.queues"]
    # a schema imports only shared, transport and schemas; the application may import anything but tools
    assert violations("services/backend/config.py", "from services.backend.window.estimator import X\n", names)
    assert not violations("services/app/system_config.py", "from services.mapping.config import MappingConfig\n", names)
    assert not violations("services/app/run_cmd.py", "from services.mapping.io import write_ply\n", names)
    assert violations("services/app/demo_cmd.py", "from tools.bench_pipeline import run_once\n", names)
