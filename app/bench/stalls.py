"""Where a run's tracing stood (`isolume bench cores`): the intervals of its ``tracing``
stage in which no tracing chunk ran on any thread, each put down to what ran instead —
a batch's commit, the next level's surface and BVH, a step's layout. On many threads
these show where the tracing pipeline waits; on two they are mostly filled by the work
waited for.
"""

from __future__ import annotations

from typing import Any

from isolume.app.bench.replay import duration

STALL_S = 0.01
"""Shortest interval without a tracing chunk that `tracing_stalls` counts, seconds."""


def tracing_stalls(timeline: dict[str, Any]) -> dict[str, Any]:
    """Where the tracing stood: the seconds of the ``tracing`` stage's visits that have
    tracing chunks (items ``trace``) during which no chunk ran, `STALL_S` or more at a
    time — ``tracing_s`` (those visits' wall), ``stalled_s``, and ``by``: per item kind,
    the seconds of the stalls in which items of that kind ran longest (``nothing`` where
    none ran): what the tracing waited for (a commit, the next level's surface and BVH, a
    layout)."""
    out: dict[str, Any] = {"tracing_s": 0.0, "stalled_s": 0.0, "by": {}}
    for stage in timeline["stages"]:
        if stage["name"] != "tracing":
            continue
        chunks = sorted((item[3], item[3] + duration(item)) for item in stage["items"]
                        if item[2] == "trace")
        if not chunks:
            continue
        out["tracing_s"] += stage["wall_s"]
        for lo, hi in _uncovered(chunks, stage["start_s"], stage["end_s"]):
            kind = _longest_kind(stage["items"], lo, hi)
            out["stalled_s"] += hi - lo
            out["by"][kind] = out["by"].get(kind, 0.0) + hi - lo
    return out


def _uncovered(spans: list[tuple[float, float]], start: float, end: float
               ) -> list[tuple[float, float]]:
    """The intervals of [start, end] of `STALL_S` or more that no span of the sorted
    (start, end) `spans` covers."""
    gaps, reached = [], start
    for lo, hi in [*spans, (end, end)]:
        if lo - reached >= STALL_S:
            gaps.append((reached, lo))
        reached = max(reached, hi)
    return gaps


def _longest_kind(items: list[list[Any]], lo: float, hi: float) -> str:
    """The kind of the items (not ``wait``) that ran longest within [lo, hi], summed over
    threads; ``nothing`` where none ran."""
    seconds: dict[str, float] = {}
    for item in items:
        overlap = min(hi, item[3] + duration(item)) - max(lo, item[3])
        if item[2] != "wait" and overlap > 0:
            seconds[item[2]] = seconds.get(item[2], 0.0) + overlap
    return max(seconds, key=seconds.get) if seconds else "nothing"


def stall_line(command: str, run_name: str, stalls: dict[str, Any]) -> str:
    """``COMMAND tracing, RUN: no chunk tracing for X s of Y s (KIND s, …)``: `stalls`
    (`tracing_stalls`) in words, the longest cause first."""
    causes = ", ".join(f"{kind} {seconds:.2f} s" for kind, seconds in
                       sorted(stalls["by"].items(), key=lambda kv: -kv[1]))
    return (f"{command} tracing, {run_name}: no chunk tracing for {stalls['stalled_s']:.2f} s "
            f"of {stalls['tracing_s']:.2f} s" + (f" ({causes})" if causes else ""))
