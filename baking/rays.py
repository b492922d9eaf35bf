"""Ray counters shared by the tracers (`trace.Scene`, `integrator`, `passes.trace_chunk`)."""

from __future__ import annotations


class RayStats:
    """Counts rays and seconds spent tracing them: inside Embree, or inside a compiled
    loop that calls Embree per ray (thread-safe enough: += on ints)."""

    def __init__(self) -> None:
        self.rays: int = 0
        self.seconds: float = 0.0

    def add(self, rays: int, seconds: float) -> None:
        self.rays += rays
        self.seconds += seconds
