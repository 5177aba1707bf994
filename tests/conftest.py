"""Test tiers and shared fixtures (tests/README.md).

Tiers, one marker per test, set here at collection:

* ``e2e``: marked by hand (``@pytest.mark.e2e`` or a module's ``pytestmark``): slow end-to-end runs.
* A tier marked by hand wins; a test with two tier markers stops the collection with a list of them.
* ``service``: marked by hand (``@pytest.mark.service``), or found: the test, one of its fixtures, or a function
  or class of its module that it calls reaches ``subprocess``, ``zenoh``, ``transport.session``/``node``/``pubsub``
  or ``tests/helpers_zenoh.py``, or requests the ``zenoh_router`` fixture.
* ``unit``: everything else. A unit test that starts a process or opens a Zenoh session anyway fails with a message
  saying so (the check below), so the tier stays what it claims: no subprocess, no Zenoh.
"""

from __future__ import annotations

import inspect
import subprocess
import types
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from helpers_data import require_real_data
from shared import paths

# what a service test reaches: modules (by import name, also when imported inside a function) and the modules
# whose functions and classes it calls
SERVICE_MODULES = frozenset({"subprocess", "zenoh", "helpers_zenoh", "tests.helpers_zenoh", "transport.session",
                             "transport.node", "transport.pubsub"})
SERVICE_FIXTURES = frozenset({"zenoh_router"})


# ----------------------------------------------------------------------------- tiers

def _code_objects(obj: object) -> Iterator[types.CodeType]:
    """Code of a function, a method or a class's methods (unwrapping decorators such as hypothesis' @given)."""
    if isinstance(obj, type):
        for v in vars(obj).values():
            yield from _code_objects(v.__func__ if isinstance(v, (staticmethod, classmethod)) else v)
        return
    inner = getattr(getattr(obj, "hypothesis", None), "inner_test", None)  # a hypothesis @given test
    obj = inspect.unwrap(inner or obj) if callable(obj) else obj
    code = getattr(obj, "__code__", None)
    if isinstance(code, types.CodeType):
        yield code


def _reaches_service(obj: object, namespace: dict, module_name: str, seen: set[int]) -> bool:
    """Whether ``obj`` (a function or class of module ``module_name`` with globals ``namespace``) refers to a
    service module, directly or through another function or class of the same module."""
    for code in _code_objects(obj):
        stack = [code]
        while stack:
            c = stack.pop()
            if id(c) in seen:
                continue
            seen.add(id(c))
            stack.extend(k for k in c.co_consts if isinstance(k, types.CodeType))  # nested functions, lambdas
            for name in c.co_names:
                if name in SERVICE_MODULES:  # `subprocess.run(...)`, `import zenoh` inside the function
                    return True
                target = namespace.get(name)
                if target is None:
                    continue
                if isinstance(target, types.ModuleType):
                    if target.__name__ in SERVICE_MODULES:
                        return True
                    continue
                owner = getattr(target, "__module__", None)
                if owner in SERVICE_MODULES:
                    return True
                if owner == module_name and (inspect.isfunction(target) or inspect.isclass(target)):
                    stack.extend(_code_objects(target))
    return False


def _is_service(item: pytest.Item) -> bool:
    if SERVICE_FIXTURES & set(getattr(item, "fixturenames", ())):
        return True
    fn = getattr(item, "function", None)
    module = getattr(item, "module", None)
    if fn is None or module is None:
        return False
    seen: set[int] = set()
    if _reaches_service(fn, vars(module), module.__name__, seen):
        return True
    info = getattr(item, "_fixtureinfo", None)  # fixtures the test uses that its own module defines (this file's
    for defs in (info.name2fixturedefs.values() if info else ()):  # are known: SERVICE_FIXTURES)
        for fd in defs:
            func = getattr(fd, "func", None)
            if func is not None and inspect.getmodule(func) is module:
                if _reaches_service(func, vars(module), module.__name__, seen):
                    return True
    return False


TIERS = ("unit", "service", "e2e")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """A test marked by hand keeps its tier; the others get one here. Two tiers on one test (e.g. ``e2e`` on a test
    of a module whose ``pytestmark`` is ``unit``) would put it in both ``-m`` selections: that stops the run."""
    clashes = []
    for item in items:
        marked = [t for t in TIERS if item.get_closest_marker(t)]
        if len(marked) > 1:
            clashes.append(f"{item.nodeid}: {', '.join(marked)}")
        elif not marked:
            item.add_marker(pytest.mark.service if _is_service(item) else pytest.mark.unit)
        elif marked == ["e2e"] and (item.get_closest_marker("processes") or _is_service(item)):
            item.add_marker(pytest.mark.processes)  # a live pipeline: `make test` runs these one at a time
    if clashes:
        raise pytest.UsageError("each test is in exactly one tier (tests/README.md); these have more than one:\n  "
                                + "\n  ".join(clashes))


class UnitTierViolation(AssertionError):
    pass


@pytest.fixture(autouse=True, scope="session")
def _matplotlib_font_cache() -> None:
    """Matplotlib's first import on a machine builds its font cache by running ``fc-list``: done once here, before
    any unit test's guard, so a unit test that plots does not fail on a fresh machine (and pass on the next run)."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import font_manager  # noqa: F401  (builds and saves the cache)


@pytest.fixture(autouse=True)
def _unit_tier_guard(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> None:
    """A unit test may not start a process nor open a Zenoh session: it fails saying to mark it ``service``."""
    if request.node.get_closest_marker("unit") is None:
        return

    def refuse(what: str) -> Callable[..., None]:
        def _refuse(*args, **kwargs) -> None:
            raise UnitTierViolation(f"{request.node.nodeid} is in the unit tier but {what}; mark it "
                                    "@pytest.mark.service (tests/README.md)")
        return _refuse

    monkeypatch.setattr(subprocess.Popen, "_execute_child", refuse("started a process"))
    try:
        import zenoh
    except ImportError:  # pragma: no cover - zenoh is a dependency
        return
    monkeypatch.setattr(zenoh, "open", refuse("opened a Zenoh session"))


# ----------------------------------------------------------------------------- clocks

class FakeClock:
    """A clock that moves only when told: ``monotonic``, ``perf_counter``, ``time``, ``time_ns``, ``thread_time``
    (as if the code under test used the CPU all the time) and ``sleep`` (which advances it), standing in for the
    ``time`` module of the code under test (``fake_clock.install``)."""

    def __init__(self, start_s: float = 1000.0) -> None:
        self.now_s = start_s

    def advance(self, seconds: float) -> None:
        assert seconds >= 0, "a monotonic clock does not go back"
        self.now_s += seconds

    def monotonic(self) -> float:
        return self.now_s

    perf_counter = monotonic
    time = monotonic
    thread_time = monotonic

    def monotonic_ns(self) -> int:
        return round(self.now_s * 1e9)

    perf_counter_ns = time_ns = monotonic_ns

    def sleep(self, seconds: float) -> None:
        self.advance(seconds)


@pytest.fixture
def fake_clock(monkeypatch: pytest.MonkeyPatch):
    """A :class:`FakeClock`; ``fake_clock.install(module)`` makes ``module.time`` (its ``import time``) this clock
    for the test, so durations, rates and windows are exact instead of depending on the machine's load."""
    clock = FakeClock()

    def install(module: types.ModuleType) -> FakeClock:
        monkeypatch.setattr(module, "time", clock)
        return clock

    clock.install = install
    return clock


# ----------------------------------------------------------------------------- data (tests/helpers_data.py)

@pytest.fixture(scope="session")
def euroc_calib() -> Path:
    """The EuRoC rig calibration folder (``calib/``): the shared one if present, else the bundled one."""
    return paths.euroc_dir() / "calib"


@pytest.fixture
def real_data() -> Callable[..., Path]:
    """``real_data(name, inside="")``: ``$SIGMASLAM_SHARED/data/real/<name>``, or skip the test saying where it was
    looked for (``helpers_data.require_real_data``)."""
    return require_real_data


@pytest.fixture(scope="session")
def cached_replica() -> Callable[..., Path]:
    """``cached_replica(sequence, scene, imu, duration_s=..., ...)``: a replica folder, generated once and cached under
    ``$SIGMASLAM_DATA/replicas`` (``services.app.synth.api.ensure_replica``; no progress bars)."""
    from services.app.synth.api import ensure_replica

    def get(*args, **kwargs) -> Path:
        kwargs.setdefault("progress", False)
        return ensure_replica(*args, **kwargs)

    return get


@pytest.fixture(scope="session")
def default_replica() -> Path:
    """The bundled default replica (25 s of V1_02 in vicon-a, real IMU), generated once if absent."""
    from services.app.synth.api import ensure_default_replica

    return ensure_default_replica(progress=False)


# ----------------------------------------------------------------------------- Zenoh

@pytest.fixture
def zenoh_router():
    """A Zenoh router in this process on a free loopback port; yields a service ``TransportConfig`` connecting to
    it, with a namespace of its own (``tests/helpers_zenoh.py``). Tests using it are in the ``service`` tier."""
    from helpers_zenoh import router

    with router() as cfg:
        yield cfg


# ----------------------------------------------------------------------------- shared scenes

@pytest.fixture(scope="session")
def o2p_room():
    """The occupancy-to-point tests' mapped room (tests/o2p_room.py) as a field message of submap 0 at 1 s, and
    its depth renderer; built once for the session."""
    import numpy as np

    from o2p_room import mapped_room
    from services.mapping.export import field_message
    from services.mapping.mesh import ChunkMesher
    from services.mapping.submaps import Submap

    store, renderer, cfg = mapped_room(0.02)
    return field_message(Submap(0, np.eye(4), 1_000_000_000, store, ChunkMesher(4)), cfg.l_min), renderer


@pytest.fixture(scope="module")
def stereo_seq():
    """The frontend tests' sequence: a stereo rig (tests/frontend_scene.py) moving through the box room, 16 frames
    rendered 50 ms apart: (room, cameras, body poses, images per frame)."""
    import frontend_scene as fs

    room = fs.BoxRoom()
    cams = fs.rig()
    poses = [fs.body_pose(k * 0.05) for k in range(16)]
    images = [[fs.render(room, c, T) for c in cams] for T in poses]
    return room, cams, poses, images
