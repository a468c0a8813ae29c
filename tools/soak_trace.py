"""The soak's per-second trace (issue 45): what happened in every second of a soak, to say what co-occurred with the
seconds in which the output rate dropped.

A run of ``tools/soak.py`` gave 58-59 Hz in nine minutes and 56.6 Hz in its tenth (220 missed ticks, the others
38-122) with nothing in its per-minute counters to say why. The trace samples once a second what a minute's line
only sums: the daemon's missed and late ticks and published frames, the rate the well-behaved client received, the
CPU of the daemon's process, of the attacker process and of everything else on the machine (``/proc/stat`` less the
two; the hypervisor's steal apart), RSS, the garbage collections of each generation and their pauses, how late the
event loop woke the sampler, which attacks ran and how much, the hostile CLI command running, IMU unplugs, SlimeVR
swarm evictions, the daemon's offset estimates and governor changes, and the log lines by logger.

:func:`trace_second` turns two :class:`Sample` readings into a second's JSON line; :func:`worst_seconds` and
:func:`co_occurred` name, for a minute below the needed rate, its worst seconds and what was unusual in them
(against the minute's median second); :func:`minute_table` prints that as the soak's per-minute verdict table.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import psutil

from mocapd.io.machine_cpu import busy_ns

REPORT_EVERY_S = 0.5
"""Seconds between the attacker process's counter reports."""
REPORT_T = "report_t"
"""The key of a report's time (``time.monotonic()`` in the attacker process) among its counters."""

#: attacker counters by the attack they count (the first matching prefix); the well-behaved client, the good
#: SlimeVR tracker and the real Zenoh host are not attacks
ATTACK_PREFIXES: tuple[tuple[str, str], ...] = (
    ("good_tracker_", ""), ("good_", ""), ("zenoh_real_", ""), ("report_t", ""), ("churn_messages", ""),
    ("churn_", "ws_churn"), ("bridge_", "bridge_datagrams"), ("slimevr_", "slimevr_garbage"),
    ("swarm_", "slimevr_swarm"), ("zenoh_rogue", "zenoh_rogue"), ("poll", "status_polling"),
    ("http_bad", "http_bad_requests"), ("viewer", "viewer_requests"), ("web_ws", "web_ws_foreign"),
    ("reset_", "reset_flood"), ("ws_reset", "ws_reset_flood"),
)  # fmt: skip


def attack_of(counter: str) -> str:
    """The attack an attacker counter counts ("" when it is no attack's: the well-behaved clients)."""
    for prefix, name in ATTACK_PREFIXES:
        if counter.startswith(prefix):
            return name
    return "other"


@dataclass
class Sample:
    """One reading of every counter the trace differences (cumulative since start, except where said)."""

    t: float
    """``time.monotonic()`` of the reading."""
    missed: int
    late: int
    published: int
    good_frames: float
    """The well-behaved client's frames at the attacker's latest report, made at ``report_t``."""
    report_t: float | None
    daemon_cpu_s: float
    machine_busy_s: float
    """Every CPU's non-idle time (``/proc/stat``: user, nice, system, irq, softirq; steal apart)."""
    machine_steal_s: float
    attacker_cpu_s: float
    rss_mib: float
    gc_collections: list[int]
    gc_pause_ms: list[float]
    attacker: dict[str, float]
    log_lines: dict[str, int]
    evictions: int
    offset_estimates: int
    offset_estimate_ms: float
    unplugs: int
    replugs: int
    cli_started: int
    cli_running: str | None
    governor_step: int | None
    governor_changes: int
    loop_late_ms: float
    """How much later than asked the event loop woke the sampler (this reading, not cumulative)."""
    stage_cpu_ms: dict[str, float] = field(default_factory=dict)
    """The tick's thread CPU by stage (the scheduler's ``cpu_s`` in /status)."""
    people: int = 0
    """People in the latest published frame (this reading)."""
    iterations: int = 0
    """Their solves' LM iterations, summed (this reading)."""
    ws_clients: int = 0
    """WebSocket clients connected (this reading)."""
    hello_skeletons: int = 0
    """Skeletons in the WebSocket hello every new client gets (this reading; per-person ones join as they appear)."""
    threads: int = 0
    """Python threads of the daemon's process (this reading)."""
    fds: int = 0
    """Its open file descriptors (this reading)."""


def machine_cpu_s() -> tuple[float, float]:
    """The machine's non-idle CPU seconds other than steal, and its steal seconds, since boot, all CPUs summed
    (``psutil.cpu_times()``: on Linux ``/proc/stat``'s first line; guest time is inside user already)."""
    t = psutil.cpu_times()
    steal = float(getattr(t, "steal", 0.0))
    return busy_ns(t) / 1e9 - steal, steal


def _delta_counts(cur: Mapping[str, float], prev: Mapping[str, float]) -> dict[str, float]:
    return {k: v - prev.get(k, 0) for k, v in cur.items() if v != prev.get(k, 0)}


def trace_second(prev: Sample, cur: Sample, t_start: float, interval_s: float) -> dict[str, Any]:
    """The trace's line for the second between two readings: rates per second, counts in it, what ran."""
    dt = max(cur.t - prev.t, 1e-9)
    t_s = cur.t - t_start
    client_hz = None
    if cur.report_t is not None and prev.report_t is not None and cur.report_t > prev.report_t:
        client_hz = round((cur.good_frames - prev.good_frames) / (cur.report_t - prev.report_t), 1)
    attacks: dict[str, int] = {}
    for key, n in _delta_counts(cur.attacker, prev.attacker).items():
        name = attack_of(key)
        if name and n > 0:
            attacks[name] = attacks.get(name, 0) + int(n)
    daemon = (cur.daemon_cpu_s - prev.daemon_cpu_s) / dt
    attacker = (cur.attacker_cpu_s - prev.attacker_cpu_s) / dt
    busy = (cur.machine_busy_s - prev.machine_busy_s) / dt
    imu = "unplug" if cur.unplugs > prev.unplugs else "replug" if cur.replugs > prev.replugs else None
    return {
        "t_s": round(t_s, 2),
        "minute": max(1, int((t_s - 1e-6) // interval_s) + 1),
        "dt_s": round(dt, 3),
        "missed": cur.missed - prev.missed,
        "late": cur.late - prev.late,
        "published_hz": round((cur.published - prev.published) / dt, 1),
        "client_hz": client_hz,
        "daemon_cpu": round(daemon, 3),
        "attacker_cpu": round(attacker, 3),
        "other_cpu": round(max(0.0, busy - daemon - attacker), 3),  # the other processes: CLI attacks, others' work
        "steal": round((cur.machine_steal_s - prev.machine_steal_s) / dt, 3),
        "rss_mib": round(cur.rss_mib, 1),
        "rss_delta_mib": round(cur.rss_mib - prev.rss_mib, 2),
        "gc_collections": [a - b for a, b in zip(cur.gc_collections, prev.gc_collections, strict=True)],
        "gc_pause_ms": [round(a - b, 2) for a, b in zip(cur.gc_pause_ms, prev.gc_pause_ms, strict=True)],
        "loop_late_ms": round(cur.loop_late_ms, 1),
        "attacks": attacks,
        "cli_running": cur.cli_running,
        "cli_started": cur.cli_started - prev.cli_started,
        "imu": imu,
        "evictions": cur.evictions - prev.evictions,
        "offset_estimates": cur.offset_estimates - prev.offset_estimates,
        "offset_estimate_ms": round(cur.offset_estimate_ms - prev.offset_estimate_ms, 1),
        "governor_step": cur.governor_step,
        "governor_changed": cur.governor_changes - prev.governor_changes,
        "log_lines": {k: int(v) for k, v in _delta_counts(cur.log_lines, prev.log_lines).items()},
        "stage_cpu_ms": {k: round(v, 1) for k, v in _delta_counts(cur.stage_cpu_ms, prev.stage_cpu_ms).items()},
        "people": cur.people,
        "iterations": cur.iterations,
        "ws_clients": cur.ws_clients,
        "hello_skeletons": cur.hello_skeletons,
        "threads": cur.threads,
        "fds": cur.fds,
    }


def _median(values: Iterable[float]) -> float:
    ordered = sorted(values)
    return ordered[len(ordered) // 2] if ordered else 0.0


def worst_seconds(seconds: list[dict[str, Any]], need_hz: float, n: int = 3) -> list[dict[str, Any]]:
    """A minute's ``n`` worst seconds: most missed ticks first, then the lowest client rate; only seconds that
    missed a tick or in which the client received less than ``need_hz``."""
    bad = [s for s in seconds if s["missed"] > 0 or (s["client_hz"] is not None and s["client_hz"] < need_hz)]
    return sorted(bad, key=lambda s: (-s["missed"], s["client_hz"] if s["client_hz"] is not None else 1e9))[:n]


def co_occurred(second: dict[str, Any], minute: list[dict[str, Any]]) -> list[str]:
    """What was unusual in ``second`` against the median second of its ``minute``: each a short phrase."""

    def med(key: str) -> float:
        return _median(float(s[key]) for s in minute)

    out: list[str] = []
    if second["other_cpu"] >= med("other_cpu") + 0.25:
        out.append(f"other processes {second['other_cpu']:.2f} cores (minute median {med('other_cpu'):.2f})")
    if second["steal"] >= 0.05:
        out.append(f"steal {second['steal']:.2f} cores")
    if second["attacker_cpu"] >= med("attacker_cpu") + 0.2:
        out.append(f"attacker process {second['attacker_cpu']:.2f} cores (median {med('attacker_cpu'):.2f})")
    if second["daemon_cpu"] >= med("daemon_cpu") + 0.2:
        out.append(f"daemon process {second['daemon_cpu']:.2f} cores (median {med('daemon_cpu'):.2f})")
    for g in (2, 1):
        count, pause = second["gc_collections"][g], second["gc_pause_ms"][g]
        if count > 0 and (g == 2 or pause >= 5.0):
            out.append(f"gc generation {g} x{count} ({pause:.0f} ms)")
    if second["loop_late_ms"] >= med("loop_late_ms") + 50.0:
        out.append(f"event loop {second['loop_late_ms']:.0f} ms late (median {med('loop_late_ms'):.0f})")
    if second["cli_running"] or second["cli_started"]:
        out.append(f"CLI attack {second['cli_running'] or 'ended'}")
    if second["imu"]:
        out.append(f"IMU {second['imu']}")
    if second["evictions"]:
        out.append(f"{second['evictions']} SlimeVR evictions")
    if second["offset_estimates"]:
        out.append(f"offset estimate ({second['offset_estimate_ms']:.0f} ms)")
    if second["governor_changed"]:
        out.append(f"governor to step {second['governor_step']}")
    if second["rss_delta_mib"] >= 2.0:
        out.append(f"RSS +{second['rss_delta_mib']:.1f} MiB")
    lines = sum(second["log_lines"].values())
    typical = _median(sum(s["log_lines"].values()) for s in minute)
    if lines >= 2 * typical + 3:
        top = max(second["log_lines"], key=second["log_lines"].__getitem__)
        out.append(f"{lines} log lines (median {typical:.0f}; most {top})")
    for stage, ms in sorted(second["stage_cpu_ms"].items()):
        usual = _median(s["stage_cpu_ms"].get(stage, 0.0) for s in minute)
        if ms >= 1.5 * usual + 20.0:
            out.append(f"tick stage {stage} {ms:.0f} ms CPU (median {usual:.0f})")
    if second["people"] != _median(s["people"] for s in minute):
        out.append(
            f"people in the latest frame: {second['people']} (usually {_median(s['people'] for s in minute):.0f})"
        )
    # attacks per second of the line (a line after a stalled loop spans more than a second)
    for name, count in sorted(second["attacks"].items()):
        usual = _median(s["attacks"].get(name, 0) / s["dt_s"] for s in minute)
        if count / second["dt_s"] >= 2 * usual + 2:
            out.append(f"attack {name} {count / second['dt_s']:.0f}/s (median {usual:.0f}/s)")
    return out


def longest_run(seconds: list[dict[str, Any]]) -> tuple[int, float | None]:
    """The longest run of consecutive seconds that each missed a tick: (seconds, the run's first ``t_s``)."""
    best, best_t, run, run_t = 0, None, 0, None
    for s in seconds:
        if s["missed"] > 0:
            run, run_t = run + 1, run_t if run else s["t_s"]
            if run > best:
                best, best_t = run, run_t
        else:
            run = 0
    return best, best_t


def minute_findings(minute: dict[str, Any], seconds: list[dict[str, Any]], need_hz: float) -> dict[str, Any]:
    """For a minute's line: its worst seconds with what co-occurred, and its longest run of seconds with missed
    ticks (filled only for a minute below ``need_hz``; empty otherwise)."""
    if minute["output_hz_client"] >= need_hz or not seconds:
        return {}
    run, run_t = longest_run(seconds)
    in_run = [s for s in seconds if run_t is not None and run_t <= s["t_s"] and s["missed"] > 0][:run]
    rest = [s for s in seconds if s not in in_run]
    return {
        # the minute as a whole (its median second): a machine loaded all minute long stands out in no one second
        "median_second": {
            k: _median(float(s[k]) for s in seconds)
            for k in ("other_cpu", "daemon_cpu", "attacker_cpu", "steal", "loop_late_ms")
        },
        "gc2_collections": sum(s["gc_collections"][2] for s in seconds),
        "worst_seconds": [
            {"t_s": s["t_s"], "missed": s["missed"], "client_hz": s["client_hz"], "with": co_occurred(s, seconds)}
            for s in worst_seconds(seconds, need_hz)
        ],
        "longest_missing_run_s": run,
        "longest_missing_run_from_t_s": run_t,
        # a dip of many seconds: the run's median second against the rest of the minute's
        "run_against_rest": {
            k: [_median(float(s[k]) for s in in_run), _median(float(s[k]) for s in rest) if rest else None]
            for k in ("missed", "other_cpu", "daemon_cpu", "attacker_cpu", "loop_late_ms")
        },
    }


def minute_table(minutes: list[dict[str, Any]], need_hz: float) -> list[str]:
    """The per-minute verdict table: each minute's client rate and missed ticks; for a minute below ``need_hz``
    its worst seconds and what co-occurred with each (from its ``worst_seconds``, :func:`minute_findings`)."""
    out = ["minute  client Hz  missed  late  verdict"]
    for m in minutes:
        held = m["output_hz_client"] >= need_hz
        out.append(f"{m['minute']:>6}  {m['output_hz_client']:>9.2f}  {m['missed_ticks']:>6}  "
                   f"{m.get('late_ticks', 0):>4}  {'held' if held else 'BELOW ' + format(need_hz, '.1f')}")  # fmt: skip
        if held:
            continue
        if not m.get("worst_seconds"):
            out.append("        no second of it in the trace missed a tick or fell below the rate")
            continue
        if "median_second" in m:
            med = m["median_second"]
            out.append(f"        its median second: other processes {med['other_cpu']:.2f} cores, daemon "
                       f"{med['daemon_cpu']:.2f}, attacker {med['attacker_cpu']:.2f}, steal {med['steal']:.2f}, "
                       f"event loop {med['loop_late_ms']:.0f} ms late; {m['gc2_collections']} generation-2 "
                       "collections")  # fmt: skip
        if m.get("longest_missing_run_s"):
            out.append(f"        longest run of seconds with missed ticks: {m['longest_missing_run_s']} s from "
                       f"t = {m['longest_missing_run_from_t_s']:.0f} s")  # fmt: skip
            ra = m.get("run_against_rest")
            if ra and next(iter(ra.values()))[1] is None:
                out.append("          (every second of the minute missed ticks)")
            elif ra:
                out.append("          its median second against the rest of the minute's: " + ", ".join(
                    f"{k} {a:.2f} / {b:.2f}" for k, (a, b) in ra.items()))  # fmt: skip
        for s in m["worst_seconds"]:
            said = "; ".join(s["with"]) or "nothing unusual recorded beside it"
            out.append(f"        t = {s['t_s']:.0f} s: {s['missed']} missed, client {s['client_hz']} Hz; with: {said}")
    return out
