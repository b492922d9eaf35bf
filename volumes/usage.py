"""What the OS says a process used: every thread's CPU time, the machine's busy and stolen
CPU on the process's cores, resident memory, child processes' CPU, and the process's
kernel time, page faults and context switches (`ProcessCounters`) — what a
`volumes.cores.Timeline` reads at each stage's ends. Linux's ``/proc`` and `resource`;
where one cannot be read, the figure is empty (0, or None where 0 would mislead).
"""

from __future__ import annotations

import os
import resource
from typing import NamedTuple


def thread_cpu() -> dict[int, float]:
    """CPU seconds of every thread of this process, by thread id (``schedstat``'s time on
    a CPU, in ns; ``stat``'s ticks where schedstat is missing)."""
    out = {}
    try:
        tids = os.listdir("/proc/self/task")
    except OSError:
        return out
    for tid in tids:
        try:
            with open(f"/proc/self/task/{tid}/schedstat") as f:
                out[int(tid)] = int(f.read().split()[0]) * 1e-9
        except (OSError, ValueError, IndexError):
            try:
                with open(f"/proc/self/task/{tid}/stat") as f:
                    fields = f.read().rsplit(")", 1)[1].split()
                out[int(tid)] = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
            except (OSError, ValueError, IndexError):
                continue
    return out


def machine_cpu(may_use: int) -> tuple[float, float] | None:
    """(busy, stolen) CPU seconds so far of the cores this process may use, summed over
    every process on the machine (``/proc/stat``: user, nice, system, irq and softirq;
    steal, the time the hypervisor gave those cores to other machines), in ticks of a
    hundredth of a second: a stage's difference is good to about its cores × 0.01 s.
    None without ``/proc/stat``, or where a cgroup quota, not the affinity, bounds the
    cores — `may_use` (`volumes.cores.available`) fewer than the affinity's: those cores
    are then shared with work that is not this process's neighbours'."""
    try:
        allowed = os.sched_getaffinity(0)
        with open("/proc/stat") as f:
            lines = [line.split() for line in f if line.startswith("cpu") and line[3].isdigit()]
    except (OSError, AttributeError, IndexError):
        return None
    if may_use < len(allowed):
        return None
    busy = stolen = 0
    for name, *fields in lines:
        if int(name[3:]) not in allowed:
            continue
        ticks = [int(v) for v in fields] + [0] * 8
        busy += ticks[0] + ticks[1] + ticks[2] + ticks[5] + ticks[6]
        stolen += ticks[7]
    tick = os.sysconf("SC_CLK_TCK")
    return busy / tick, stolen / tick


def resident_bytes() -> int:
    """This process's resident memory now, in bytes (``/proc/self/statm``; 0 without)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return 0


def peak_resident_bytes() -> int:
    """This process's peak resident memory so far, in bytes (the OS's high-water mark)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def children_cpu() -> float:
    """CPU seconds of this process's child processes: those waited for (`resource`) and
    those still running (their ``/proc`` stat, and their children's)."""
    used = resource.getrusage(resource.RUSAGE_CHILDREN)
    return used.ru_utime + used.ru_stime + sum(_live_cpu(pid) for pid in _children(os.getpid()))


def _children(pid: int) -> list[int]:
    """Process ids of `pid`'s children (every thread's ``children`` list)."""
    found = []
    try:
        for tid in os.listdir(f"/proc/{pid}/task"):
            with open(f"/proc/{pid}/task/{tid}/children") as f:
                found += [int(c) for c in f.read().split()]
    except (OSError, ValueError):
        pass
    return found


def _live_cpu(pid: int) -> float:
    """CPU seconds of the running process `pid` and its own descendants."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        own = (int(fields[11]) + int(fields[12]) + int(fields[13]) + int(fields[14]))
        seconds = own / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return 0.0
    return seconds + sum(_live_cpu(child) for child in _children(pid))


class ProcessCounters(NamedTuple):
    """The OS's counts for this process's own threads so far (`resource.getrusage`; child
    processes' are not in them): CPU seconds in user space and in the kernel (page
    faults, system calls, the GIL's and the pool's futex wake-ups; where the OS splits
    the two by sampling its clock ticks, good to a tick or so a thread), page faults served
    from memory (minor: a page first touched, or mapped again) and from disk (major), and
    context switches where a thread waited (voluntary: a lock, the GIL, I/O) or was
    preempted (involuntary: more threads ready than cores)."""

    user_s: float
    system_s: float
    minor_faults: int
    major_faults: int
    voluntary_switches: int
    involuntary_switches: int

    def since(self, earlier: ProcessCounters) -> ProcessCounters:
        """What was counted between `earlier` and these."""
        return ProcessCounters(*(now - then for now, then in zip(self, earlier, strict=True)))


def process_counters() -> ProcessCounters:
    """`ProcessCounters` of this process now."""
    used = resource.getrusage(resource.RUSAGE_SELF)
    return ProcessCounters(used.ru_utime, used.ru_stime, used.ru_minflt, used.ru_majflt,
                           used.ru_nvcsw, used.ru_nivcsw)
