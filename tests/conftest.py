"""Shared fixtures: a headless OSMesa GL context, the optional ../shared data folder, and
the failures a lattice's save meets (a Ctrl-C, a full disk)."""

from __future__ import annotations

import errno
import os
import signal
import time
from pathlib import Path

import pytest

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
"""``<clone>/../shared/data``: real volumes and probes, present on developer machines."""


def shared_file(*parts: str) -> Path:
    """Path of a file under ../shared/data, or skip the test when it is absent."""
    path = SHARED.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"{path} not present (../shared/data is optional)")
    return path


@pytest.fixture(scope="session")
def _gl_session():
    """One OSMesa context for the whole session (tests run on OSMesa, as CI does)."""
    from isolume.app.render.glcontext import create_headless

    context = create_headless("osmesa")
    yield context
    context.release()


@pytest.fixture
def gl(_gl_session):
    """The session's OSMesa context, current on this thread (a test may have made its own
    context current, e.g. through the CLI)."""
    _gl_session.make_current()
    return _gl_session.ctx


@pytest.fixture
def renderer(gl):
    """A fresh SurfaceRenderer on the session context; checks GL errors around the test."""
    from isolume.app.render.renderer import SurfaceRenderer

    assert gl.error == "GL_NO_ERROR"
    r = SurfaceRenderer(gl)
    yield r
    r.release()
    assert gl.error == "GL_NO_ERROR"


FIRST = ("test_napari.py",)
"""Test modules that run before all others: napari's Qt window draws with the GL context
its widget makes current, which a headless context made current on the same thread by an
earlier test (EGL, OSMesa) would replace."""


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Run the `FIRST` modules' tests first, in their order; the rest as collected."""
    items.sort(key=lambda item: item.path.name not in FIRST)


@pytest.fixture
def ctrl_c_during_save(monkeypatch):
    """``ctrl_c_during_save(presses)``: from then on `PlanLattice.save` sends this process
    `presses` SIGINTs (a user's Ctrl-C) before it writes."""
    from isolume.baking.plan_lattice import PlanLattice

    original = PlanLattice.save

    def arm(presses: int) -> None:
        def pressed(self, path):
            for _ in range(presses):
                os.kill(os.getpid(), signal.SIGINT)
            original(self, path)

        monkeypatch.setattr(PlanLattice, "save", pressed)

    return arm


@pytest.fixture
def stopped_after():
    """``stopped_after(proc, marker, signum, wait=0.0)``: read the text stderr of the
    process `proc` up to a line holding `marker`, wait `wait` seconds, send it `signum`,
    and return (its exit status, all its stderr); it is killed whatever happens."""

    def stop(proc, marker: str, signum: int, wait: float = 0.0) -> tuple[int, str]:
        seen: list[str] = []
        try:
            for line in proc.stderr:
                seen.append(line)
                if marker in line:
                    break
            time.sleep(wait)
            proc.send_signal(signum)
            _, rest = proc.communicate(timeout=60)
        finally:
            proc.kill()
        return proc.returncode, "".join(seen) + rest

    return stop


@pytest.fixture
def disk_full(monkeypatch):
    """``disk_full()``: from then on writing a lattice file fails half-way as a full disk
    makes it fail (ENOSPC)."""
    from isolume.baking import lattice_file

    def full(zf, members):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    return lambda: monkeypatch.setattr(lattice_file, "_write_deflated", full)
