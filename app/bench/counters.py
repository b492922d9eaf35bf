"""``bench cores``: what the OS counted in a run — its kernel time, page faults and context
switches, per stage and whole (`isolume.volumes.usage.ProcessCounters`, recorded per
stage by the timeline) — which says where CPU time that grows with the threads goes:
kernel time with page faults (memory mapped and unmapped per item), waits (the GIL, a
lock), or preemptions (more threads ready than cores)."""

from __future__ import annotations

from typing import Any

from isolume.volumes.usage import ProcessCounters

COUNTERS = ProcessCounters._fields
"""The counters a timeline's stages hold (the fields of `ProcessCounters`), which
``bench cores`` adds up per stage and over the run (`aggregate`, `whole`)."""
SHOWN_STAGES = 3
"""Stages named in a run's line: those of the most kernel time."""


def _thousands(count: float) -> str:
    """``756 k`` from 756 000, ``12`` from 12."""
    return f"{count / 1000:.1f} k" if count >= 1000 else f"{count:.0f}"


def counters_line(command: str, run_name: str, stages: dict[str, dict[str, Any]],
                  whole: dict[str, Any]) -> str:
    """One run's line: its kernel time against its CPU time, page faults and context
    switches (`whole`: its `COUNTERS` added up), and the stages of the most kernel time
    with their faults (`stages`: per stage name, as ``bench cores``'s `aggregate` adds
    them up)."""
    w = whole
    cpu = w["user_s"] + w["system_s"]
    share = f" ({w['system_s'] / cpu:.1%})" if cpu > 0 else ""
    busiest = sorted(stages.items(), key=lambda kv: -kv[1]["system_s"])
    stages = ", ".join(f"{name} {f['system_s']:.2f} s ({_thousands(f['minor_faults'])} faults)"
                       for name, f in busiest[:SHOWN_STAGES] if f["system_s"] > 0)
    return (f"{command} kernel, {run_name}: {w['system_s']:.2f} s of its {cpu:.2f} s CPU in "
            f"the kernel{share}, {_thousands(w['minor_faults'])} page faults "
            f"({w['major_faults']:.0f} from disk), {_thousands(w['voluntary_switches'])} "
            f"waits and {_thousands(w['involuntary_switches'])} preemptions"
            + (f"; most kernel time: {stages}" if stages else ""))
