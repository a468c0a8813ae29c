"""Holding mocapd to a CPU budget (mocapd.io.cpu_budget): the real cgroup of this machine, in child processes so
that the test runner itself is never held."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

from mocapd.io.cpu_budget import find_hierarchies

MOUNTS_V1 = textwrap.dedent("""\
    30 25 0:26 / /sys/fs/cgroup rw,relatime - tmpfs tmpfs rw,mode=755
    31 30 0:27 / /sys/fs/cgroup/cpu rw,relatime - cgroup cgroup rw,cpu
    32 30 0:28 / /sys/fs/cgroup/cpuacct rw,relatime - cgroup cgroup rw,cpuacct
    33 30 0:29 / /sys/fs/cgroup/unified rw,relatime - cgroup2 cgroup2 rw
""")
CGROUP_V1 = "2:cpuacct:/\n1:cpu:/user.slice\n0::/\n"


def test_the_v1_cpu_hierarchy_is_found_from_the_process_tables(tmp_path: Path) -> None:
    found = find_hierarchies(CGROUP_V1, MOUNTS_V1)
    assert [(h.version, str(h.parent)) for h in found] == [(1, "/sys/fs/cgroup/cpu/user.slice")]


def test_a_v2_cgroup_with_the_cpu_controller_comes_first(tmp_path: Path) -> None:
    here = tmp_path / "user.slice"
    here.mkdir()
    (here / "cgroup.controllers").write_text("cpuset cpu io memory pids\n")
    mounts = f"40 25 0:30 / {tmp_path} rw - cgroup2 cgroup2 rw\n" + MOUNTS_V1
    found = find_hierarchies("1:cpu:/user.slice\n0::/user.slice\n", mounts)
    assert [h.version for h in found] == [2, 1] and found[0].parent == here
    (here / "cgroup.controllers").write_text("memory pids\n")  # no cpu controller there: v1 only
    assert [h.version for h in find_hierarchies("1:cpu:/user.slice\n0::/user.slice\n", mounts)] == [1]


HELD = """
import json, os, subprocess, sys, time
from mocapd.io import cpu_budget

def cgroup(pid):
    return [l for l in open(f"/proc/{pid}/cgroup").read().splitlines() if l.split(":")[1] in ("cpu", "cpu,cpuacct", "")]

with cpu_budget.held(0.1) as b:
    inside = cgroup(os.getpid())
    camera = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    born = cgroup(camera.pid)
    cpu_budget.exempt(camera.pid)  # a fake camera: out of the budget
    exempted = cgroup(camera.pid)
    t = time.monotonic()
    while time.monotonic() - t < 1.0:
        pass
    report = b.describe()
camera.kill()
print(json.dumps({"inside": inside, "born": born, "exempted": exempted, "after": cgroup(os.getpid()),
                  "report": report, "removed": not os.path.exists(report["cgroup"])}))
"""


def test_the_process_is_held_its_children_exempted_and_the_cgroup_removed() -> None:
    out = subprocess.run([sys.executable, "-c", HELD], capture_output=True, text=True, timeout=60, check=False)
    assert out.returncode == 0, out.stderr[-2000:]
    r = json.loads(out.stdout)
    name = Path(r["report"]["cgroup"]).name
    assert name.startswith("mocapd-budget-") and r["report"]["cores"] == 0.1
    assert r["report"]["mechanism"] in ("cgroup v1 cpu.cfs_quota_us", "cgroup v2 cpu.max")
    assert any(line.endswith(name) for line in r["inside"])  # the process ran in the budget's cgroup
    assert any(line.endswith(name) for line in r["born"])  # a child starts inside it ...
    assert not any(line.endswith(name) for line in r["exempted"])  # ... until exempted
    assert not any(line.endswith(name) for line in r["after"]) and r["removed"]
    # A second of spinning at 10 % of a core: the kernel ran it in its periods and throttled most of them; the
    # quota holds two of the kernel's slices (a 100 ms period for the default 5 ms slice).
    report = r["report"]
    assert report["periods"] >= 1 and report["throttled_periods"] >= 1, report
    assert report["quota_us"] == round(0.1 * report["period_us"]) >= 2 * report["slice_us"], report


def test_the_period_is_10_ms_unless_the_quota_would_hold_under_two_bandwidth_slices(tmp_path: Path) -> None:
    from mocapd.io.cpu_budget import bandwidth_slice_us, period_for

    assert period_for(2.0, 5000) == period_for(1.0, 5000) == 10_000  # a 10 ms quota: two 5 ms slices
    assert period_for(0.8, 5000) == 12_500 and period_for(0.4, 5000) == 25_000  # 10 ms quotas
    assert period_for(0.4, 1000) == 10_000 and period_for(0.1, 1000) == 20_000
    knob = tmp_path / "sched_cfs_bandwidth_slice_us"
    knob.write_text("3000\n")
    assert bandwidth_slice_us(knob) == 3000
    assert bandwidth_slice_us(tmp_path / "absent") == 5000  # the kernel's default where it cannot be read


def test_the_quota_a_process_runs_under_is_read_from_its_cgroup(tmp_path: Path) -> None:
    """What the detector sizes its threads by (``detector_pool.process_cores``): a v2 ``cpu.max`` quota, none
    ("max"), and a v1 CFS quota."""
    from mocapd.io.cpu_budget import quota_cores

    here = tmp_path / "v2" / "app.slice"
    here.mkdir(parents=True)
    (here / "cgroup.controllers").write_text("cpu memory\n")
    (here / "cpu.max").write_text("80000 100000\n")
    mounts = f"40 25 0:30 / {tmp_path / 'v2'} rw - cgroup2 cgroup2 rw\n"
    assert quota_cores("0::/app.slice\n", mounts) == 0.8
    (here / "cpu.max").write_text("max 100000\n")
    assert quota_cores("0::/app.slice\n", mounts) is None
    v1 = tmp_path / "cpu" / "budget"
    v1.mkdir(parents=True)
    (v1 / "cpu.cfs_quota_us").write_text("15000\n")
    (v1 / "cpu.cfs_period_us").write_text("10000\n")
    mounts_v1 = f"31 30 0:27 / {tmp_path / 'cpu'} rw,relatime - cgroup cgroup rw,cpu\n"
    assert quota_cores("1:cpu:/budget\n", mounts_v1) == 1.5
