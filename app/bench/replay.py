"""The replay of `isolume bench cores`: a one-thread run's timeline (`volumes.cores.Timeline`)
played again on more simulated threads than the machine has.

Per stage visit, the glue between its items (its wall at one thread less its items'
seconds, taken as serial) and its items as units of work run one after another — a batch
(one parallel call, or the tracing chunks of a level's steps queued side by side)
list-scheduled greedily in recorded order, a run of consecutive single items of one
kind scheduled together. One thread runs a `for_ranges` call as a single item; where the
run with the most threads cut the same stage's call of that kind into items, the
one-thread item is cut in the same shares (that cut is the one any thread count gets,
unless it reached `cores.ITEMS_PER_CALL`: then more threads would cut finer, and the
replay is pessimistic). Gaps of at most `ITEM_GAP_S` between a unit's items are the
items' own overhead. Work done beside the critical path (`volumes.cores.beside`) runs
beside it: on a lane until the command waits for it by name — from where the unit of
work it was recorded beside began (the next step laid out while this one traces), else
from where it comes in order — else sharing the next unit's threads. A lane is one
helper thread (`LANES`): work on it runs in turn.
Items parallel inside (`INNER_PARALLEL`) are shortened as they scaled when measured, and
checkpoints, made every `baking.saves.CHECKPOINT_S` seconds, come as often as the
predicted wall time allows.
"""

from __future__ import annotations

import heapq
from collections import Counter
from collections.abc import Callable
from typing import Any

INNER_PARALLEL = {"bvh": "bvh", "scene": "bvh", "save": "save", "checkpoint": "save",
                  "gl": "gl"}
"""Kinds of item that are parallel inside (an Embree BVH build runs on Embree's own
`--workers` threads, a scene built ahead is mostly its BVH build, a lattice's save
deflates its pieces on the pool, a picture drawn off-screen is rasterised on Mesa's
llvmpipe threads): the replay shortens them by Amdahl's law, with the
serial fraction fitted to how much faster the items of the kind named here ran with the
most threads measured (`inner_factors`; a checkpoint is the same save as the last one,
which shares no core with tracing)."""
LANES = {"warm up": "warm up"}
"""The lane of each kind of work done beside that the command waits for by name (the
thread it runs on: a `baking.backend.ThreadBackend` loads its compiled code on a thread of
its own); other kinds share the helper's ("helper")."""
ITEM_GAP_S = 0.005
"""Gaps up to this long between consecutive items of one unit of work (`work_units`) are
the items' own overhead — handing an item out, a progress update after it — done by the
thread that ran it, not glue that runs alone."""


def duration(item: list[Any]) -> float:
    """Seconds of a timeline item ``[batch, tid, kind, start_s, end_s]``."""
    return max(0.0, item[4] - item[3])


def outside_stages_s(timeline: dict[str, Any]) -> float:
    """Seconds of the timeline in no stage (before the first, between two)."""
    return max(0.0, timeline["wall_s"] - sum(s["wall_s"] for s in timeline["stages"]))


def makespan(durations: list[float], n: int) -> float:
    """Seconds until `n` threads finish `durations`, each item in order given to the thread
    free first (greedy list scheduling)."""
    free = [0.0] * max(1, min(n, len(durations)))
    for seconds in durations:
        heapq.heapreplace(free, free[0] + seconds)
    return max(free, default=0.0)


def batch_sizes(timeline: dict[str, Any]) -> Counter[int]:
    """Items per batch id over the whole timeline (1: a single item)."""
    return Counter(item[0] for stage in timeline["stages"] for item in stage["items"])


def is_beside(item: list[Any]) -> bool:
    """Was the item done beside the critical path (`volumes.cores.beside`)?"""
    return len(item) > 5 and bool(item[5])


def inner_factors(one: dict[str, Any], most: dict[str, Any]) -> dict[str, float]:
    """Per kind of `INNER_PARALLEL`: the serial fraction f of its items (Amdahl's law fitted
    to their mean seconds on one thread against on the `most` run's N threads — of the
    items not done beside, which shared no core with other work, where both runs have
    some, else of all; 1 where no run has more threads or no item of the kind)."""
    n = most["threads"]
    out = {}
    for kind, measured in INNER_PARALLEL.items():
        found = [[item for stage in run["stages"] for item in stage["items"]
                  if item[2] == measured] for run in (one, most)]
        alone = [[item for item in items if not is_beside(item)] for items in found]
        t1, tn = (sum(map(duration, items)) / len(items) if items else 0.0
                  for items in (alone if all(alone) else found))
        if n <= 1 or t1 <= 0 or tn <= 0:
            out[kind] = 1.0
            continue
        out[kind] = min(1.0, max(0.0, (n * tn / t1 - 1) / (n - 1)))
    return out


def work_units(items: list[list[Any]], sizes: Counter[int] | None = None,
               split: Callable[[str], list[float] | None] | None = None,
               carried: list[float] | None = None,
               seconds_of: Callable[[list[Any]], float] = duration) -> list[list[float]]:
    """The durations of each unit of `work_events` (its units alone)."""
    return [event[1] for event in work_events(items, sizes, split, carried, seconds_of)
            if event[0] == "unit"]


def work_events(items: list[list[Any]], sizes: Counter[int] | None = None,
                split: Callable[[str], list[float] | None] | None = None,
                carried: list[float] | None = None,
                seconds_of: Callable[[list[Any]], float] = duration,
                recorded: list[float] | None = None,
                laned: frozenset[int] = frozenset()) -> list[tuple]:
    """The items of a stage visit as events in order: ``("unit", durations, key)``, the
    units run one after another, each the durations of items that may run side by side —
    a batch's items (placed at its first item; key ``("batch", id)``), a run of
    consecutive single items of one kind (``("single", kind)``), or a single item that
    `split(kind)` cuts into shares (its own unit, ``("split", id)``); ``("lane", batch,
    seconds, beside, kind)``, work of `kind` done beside that the command waits for later
    (its batch in `laned`: a "wait" item marks where), `beside` the index of the unit whose
    recorded items ran while it began (the latest such; None: none); ``("wait", batch)``,
    that mark.

    An item that follows its unit's last item within `ITEM_GAP_S` takes the gap into its
    seconds. Other items done beside (`is_beside`: a batch committed while the next is
    traced, which one thread records after that next step's chunks) join the unit before
    them in the visit, as the threads that run it would share the work, or else the next
    one; `carried` holds those not yet placed (from earlier visits), taken out as they
    are, and those left at the end go back into it (None: they make a unit at the end).
    `sizes`: items per batch id (default: counted in `items`);
    `seconds_of`: an item's seconds (`duration`); `recorded`, where given, gets each
    item's recorded seconds with the gap it took (what the stage's wall holds besides
    glue)."""
    sizes = sizes if sizes is not None else Counter(item[0] for item in items)
    waiting = carried if carried is not None else []
    events: list[tuple] = []
    batches: dict[int, int] = {}  # batch id: its unit's event index
    began: dict[int, float] = {}  # by unit event index: when its first item began
    ended: dict[int, float] = {}  # by unit event index: when its last item ended

    def begin(key: tuple, durations: list[float], item: list[Any]) -> None:
        events.append(("unit", [*waiting, *durations], key))
        waiting.clear()
        began[len(events) - 1], ended[len(events) - 1] = item[3], item[4]

    def join(at: int, item: list[Any], seconds: float) -> None:
        gap = item[3] - ended[at]
        gap = gap if 0 < gap <= ITEM_GAP_S else 0.0
        events[at][1].append(seconds + gap)
        ended[at] = max(ended[at], item[4])
        if recorded is not None:
            recorded[-1] += gap

    for item in sorted(items, key=lambda item: item[3]):
        batch, kind, seconds = item[0], item[2], seconds_of(item)
        if kind == "wait":
            events.append(("wait", batch))
            continue
        if recorded is not None:
            recorded.append(duration(item))
        if is_beside(item):
            if batch in laned:
                events.append(("lane", batch, seconds, item[3], kind))
            elif ended:  # a unit so far in this visit: the last one begun
                events[max(ended)][1].append(seconds)
            else:
                waiting.append(seconds)
            continue
        last = events[-1] if events else None
        if sizes[batch] > 1:
            if batch in batches:
                join(batches[batch], item, seconds)
            else:
                begin(("batch", batch), [seconds], item)
                batches[batch] = len(events) - 1
            continue
        shares = split(kind) if split is not None else None
        if shares:
            begin(("split", batch), [seconds * share for share in shares], item)
        elif last is not None and last[0] == "unit" and last[2] == ("single", kind) \
                and not waiting:
            join(len(events) - 1, item, seconds)
        else:
            begin(("single", kind), [seconds], item)
    if carried is None and waiting:
        events.append(("unit", list(waiting), ("beside",)))
    return [_beside_unit(event, index, began, ended) if event[0] == "lane" else event
            for index, event in enumerate(events)]


def _beside_unit(lane: tuple, index: int, began: dict[int, float],
                 ended: dict[int, float]) -> tuple:
    """`lane` (``("lane", batch, seconds, start, kind)``, the `index`-th event) with `start`
    replaced by the index of the latest unit before it whose recorded items span that
    start (`began`, `ended`: by unit index), or None."""
    start = lane[3]
    inside = [unit for unit in began if unit < index and began[unit] <= start <= ended[unit]]
    return (*lane[:3], max(inside) if inside else None, *lane[4:])


def split_hints(timeline: dict[str, Any]) -> dict[tuple[str, str], list[list[float]]]:
    """Per (stage, kind): the shares of the items of each batch of that kind, in order (how
    a run with several threads cut its parallel calls; items done beside left out)."""
    sizes = batch_sizes(timeline)
    hints: dict[tuple[str, str], list[list[float]]] = {}
    for stage in timeline["stages"]:
        batches: dict[int, tuple[str, list[float]]] = {}
        for item in sorted(stage["items"], key=lambda item: item[3]):
            if sizes[item[0]] > 1 and not is_beside(item):
                batches.setdefault(item[0], (item[2], []))[1].append(duration(item))
        for kind, seconds in batches.values():
            if sum(seconds) > 0:
                hints.setdefault((stage["name"], kind), []).append(
                    [s / sum(seconds) for s in seconds])
    return hints


def _splitter(stage: str, hints: dict, taken: Counter) -> Callable[[str], list[float] | None]:
    """`work_units`'s `split` for `stage`: the k-th single item of a kind gets the shares of
    the k-th batch of that kind in `hints` (the last one's past the end)."""
    def split(kind: str) -> list[float] | None:
        found = hints.get((stage, kind))
        if not found:
            return None
        k = taken[stage, kind]
        taken[stage, kind] += 1
        return found[min(k, len(found) - 1)]
    return split


def _on_threads(n: int, inner: dict[str, float] | None) -> Callable[[list[Any]], float]:
    """An item's seconds on `n` simulated threads: its own, or, for a kind parallel inside
    (`inner`: its serial fraction f), its own × (f + (1 − f) / n)."""
    inner = inner or {}

    def seconds(item: list[Any]) -> float:
        f = inner.get(item[2])
        return duration(item) if f is None else duration(item) * (f + (1 - f) / n)
    return seconds


class _Play:
    """Where a replay is: the simulated clock (seconds), when each lane of work done beside
    is free (by `LANES` name), when each laned batch is done, the beside work not yet
    placed."""

    def __init__(self) -> None:
        self.clock = 0.0
        self.lanes: dict[str, float] = {}
        self.ready: dict[int, float] = {}
        self.carried: list[float] = []


def replay_stage(stage: dict[str, Any], n: int, sizes: Counter[int] | None = None,
                 split: Callable[[str], list[float] | None] | None = None,
                 play: _Play | None = None, inner: dict[str, float] | None = None,
                 laned: frozenset[int] = frozenset()) -> float:
    """Predicted seconds of one stage visit (of a one-thread run) on `n` threads: its glue
    (wall less its items' seconds as recorded, at least 0), then its `work_events` in
    order — a unit's makespan; work on its lane (one more thread, `LANES`) from when it is
    issued or the lane is free, its share of the `n` cores (seconds / n) added to the
    clock; a wait until the lane has done that batch. `play` carries the clock and the
    lanes from visit to visit; `inner` as `replay` takes it. Work for a lane recorded while a
    unit's items ran is issued where that unit began."""
    play = play if play is not None else _Play()
    began = play.clock
    recorded: list[float] = []
    events = work_events(stage["items"], sizes, split, play.carried, _on_threads(n, inner),
                         recorded, laned)
    play.clock += max(0.0, stage["wall_s"] - sum(recorded))
    started: dict[int, float] = {}  # by unit event index: the clock when it began
    for index, event in enumerate(events):
        if event[0] == "unit":
            started[index] = play.clock
            play.clock += makespan(event[1], n)
        elif event[0] == "lane":
            issued = started.get(event[3], play.clock) if event[3] is not None else play.clock
            lane = LANES.get(event[4], "helper")
            play.lanes[lane] = max(issued, play.lanes.get(lane, 0.0)) + event[2]
            play.ready[event[1]] = play.lanes[lane]
            play.clock += event[2] / n
        else:
            play.clock = max(play.clock, play.ready.get(event[1], play.clock))
    return play.clock - began


def replay(timeline: dict[str, Any], n: int,
           hints: dict[tuple[str, str], list[list[float]]] | None = None,
           inner: dict[str, float] | None = None) -> dict[str, float]:
    """Predicted seconds of each stage (visits added up by name) of the one-thread
    `timeline` on `n` threads, and of the whole command ("whole": the stages and the
    time outside them). `hints`: `split_hints` of a run with several threads; `inner`:
    `inner_factors`. Work done beside that the command waits for by name (a "wait" item)
    runs on a lane of its own until then; other work done beside joins the next unit of
    work, in a later stage if need be; what is left at the end runs on its own, in the
    last stage. A bake's checkpoints come as often as its tracing's predicted seconds
    allow (`checkpoints_kept`); the replay keeps that many of the recorded ones, first
    first (`thinned`)."""
    if any(item[2] == "checkpoint" for stage in timeline["stages"] for item in stage["items"]):
        timeline = thinned(timeline, checkpoints_kept(timeline, n, hints, inner))
    sizes, taken, play = batch_sizes(timeline), Counter(), _Play()
    laned = frozenset(item[0] for stage in timeline["stages"] for item in stage["items"]
                      if item[2] == "wait")
    out: dict[str, float] = {}
    for stage in timeline["stages"]:
        split = _splitter(stage["name"], hints or {}, taken)
        out[stage["name"]] = out.get(stage["name"], 0.0) + replay_stage(
            stage, n, sizes, split, play, inner, laned)
    if play.carried and timeline["stages"]:
        out[timeline["stages"][-1]["name"]] += makespan(play.carried, n)
    out["whole"] = sum(out.values()) + outside_stages_s(timeline)
    return out


def checkpoints_kept(timeline: dict[str, Any], n: int,
                     hints: dict[tuple[str, str], list[list[float]]] | None,
                     inner: dict[str, float] | None) -> int:
    """How many checkpoints a bake makes on `n` threads: its tracing's predicted seconds
    (without checkpoints) over `baking.saves.Checkpoints`' spacing — `CHECKPOINT_S`, or
    1 / `SAVE_SHARE` times a checkpoint's predicted seconds where that is longer."""
    from isolume.baking.saves import CHECKPOINT_S, SAVE_SHARE

    tracing = replay(thinned(timeline, 0), n, hints, inner).get("tracing", 0.0)
    saves = [_on_threads(n, inner)(item) for stage in timeline["stages"]
             for item in stage["items"] if item[2] == "checkpoint"]
    spacing = max(CHECKPOINT_S, sum(saves) / len(saves) / SAVE_SHARE)
    return int(tracing // spacing)


def thinned(timeline: dict[str, Any], keep: int) -> dict[str, Any]:
    """`timeline` with only its first `keep` checkpoints: the others' items left out and
    their seconds taken off their stages' (and the whole timeline's) wall."""
    out, kept = dict(timeline, stages=[]), 0
    for stage in timeline["stages"]:
        items, dropped = [], 0.0
        for item in sorted(stage["items"], key=lambda item: item[3]):
            if item[2] == "checkpoint":
                kept += 1
                if kept > keep:
                    dropped += duration(item)
                    continue
            items.append(item)
        out["stages"].append(dict(stage, items=items, wall_s=stage["wall_s"] - dropped))
        out["wall_s"] -= dropped
    return out
