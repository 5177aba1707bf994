"""The supervisor's priorities (services/app/scheduling.py): which nice a child gets where a negative one is or is
not allowed, and what is read from /proc. The children themselves: tests/test_supervisor.py."""

from __future__ import annotations

import os

import pytest

from services.app.scheduling import autogroup_nice, has_cap_sys_nice, lowest_nice, resolve_nice, set_autogroup_nice


def test_resolve_nice_adds_clamps_and_says_why_when_not_allowed():
    assert resolve_nice(-10, base=0, lowest=-20) == (-10, "")
    assert resolve_nice(19, base=5, lowest=0) == (19, "")  # 24 clamped to 19: lowering priority is always allowed
    assert resolve_nice(-5, base=10, lowest=10) == (10, resolve_nice(-5, base=10, lowest=10)[1])
    nice, why = resolve_nice(-10, base=0, lowest=0)  # an unprivileged user: the path to a pose runs at nice 0
    assert nice == 0 and "nice -10 is not permitted" in why and "CAP_SYS_NICE" in why and "ulimit -e 30" in why
    nice, why = resolve_nice(-10, base=0, lowest=-5)  # a nice limit of 25 (limits.conf): as low as it allows
    assert nice == -5 and "so nice -5" in why
    assert resolve_nice(-30, base=0, lowest=-20) == (-20, "")


def test_cap_sys_nice_is_read_from_the_effective_set(tmp_path):
    status = tmp_path / "status"
    status.write_text("Name:\tx\nCapInh:\t0000000000000000\nCapEff:\t0000000000800000\n")  # bit 23 only
    assert has_cap_sys_nice(str(status))
    status.write_text("Name:\tx\nCapEff:\t00000000007fffff\n")  # every capability below 23
    assert not has_cap_sys_nice(str(status))
    assert not has_cap_sys_nice(str(tmp_path / "missing"))


def test_lowest_nice_here_agrees_with_the_capability():
    low = lowest_nice()
    assert -20 <= low <= os.getpriority(os.PRIO_PROCESS, 0)
    if has_cap_sys_nice():
        assert low == -20


def test_autogroup_nice_where_there_is_none(tmp_path):
    assert not set_autogroup_nice(5, path=str(tmp_path / "no" / "autogroup"), tries=2)
    f = tmp_path / "autogroup"  # a plain file stands in for /proc/self/autogroup: what is written is the nice
    assert set_autogroup_nice(7, path=str(f)) and f.read_text() == "7"


def test_autogroup_nice_reads_the_kernels_line_and_nothing_else(tmp_path):
    f = tmp_path / "autogroup"
    f.write_text("/autogroup-42 nice -5\n")
    assert autogroup_nice(str(f)) == -5
    for text in ("", "garbage", "/autogroup-1 nice x"):  # empty: a process in a cgroup of its own (a container, CI)
        f.write_text(text)
        assert autogroup_nice(str(f)) is None
    assert autogroup_nice(str(tmp_path / "missing")) is None


@pytest.mark.skipif(autogroup_nice() is None, reason="this process has no autogroup (autogroups off, or in a cgroup)")
def test_autogroup_reads_back_as_a_nice():
    text = open("/proc/self/autogroup").read()
    assert text.startswith("/autogroup-") and "nice" in text
