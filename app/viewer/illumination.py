"""The viewer's global illumination: the lattice it shows and the lazy bake that fills it.

`Illumination` decides, from ``--lattice`` and ``--no-bake``, whether a lattice from a file
is shown as is or baked further, or a new one is baked lazily (`app.viewer.bake_client`:
a separate process writing into a `SharedLattice`); it tells that bake what is on screen
and what a screenshot of it shows once the view settles, brings the texels it commits to
the GPU (`app.viewer.draw.Drawing`), and answers what the panel, scripts and ``--stats``
ask about it.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict
from typing import TYPE_CHECKING, Any

import numpy as np

from isolume import volumes
from isolume.app.viewer.bake_client import BakeLink, SharedLattice, lattice_meta, range_warning
from isolume.app.viewer.command import Options
from isolume.app.viewer.draw import UPLOAD_BUDGET_S, UPLOAD_FIRST_S, Drawing
from isolume.app.viewer.state import ViewerError, ViewerState

if TYPE_CHECKING:
    from isolume.baking.lattice import Lattice
    from isolume.baking.view_texels import HeldLattice, LatticeOnFile

SETTLE_S = 0.2
"""The view must be still this long before the visible texels are measured again."""


def _complete(lattice, samples: int) -> bool:
    """Whether every active texel of the lattice file `lattice` (a `LatticeOnFile`) has
    `samples` paths (read from the file: its samples and active flags only)."""
    _, held = lattice.file.read_texels(None, ("samples", "active"))
    return bool((held["samples"][held["active"]] >= samples).all())


def lattice_modes() -> tuple[str, ...]:
    """The shading modes that read a lattice."""
    from isolume.app.render.settings import LATTICE_MODES

    return tuple(LATTICE_MODES)


class Illumination:
    """The lattice shown and its lazy bake (see the module docstring).

    Attributes:
        shared: the lattice in shared memory that a lazy bake fills (None: no lazy bake
            started).
        bake: the link to the lazy-bake process (None: none runs).
        static_lattice: a complete lattice from a file, shown as is: its computed texels
            (a `baking.view_texels.HeldLattice`; None: none).
        static_file: that file, opened (`baking.view_texels.LatticeOnFile`), for a bake
            of its turned light.
        relit_file: `static_lattice` is re-baked lazily for a light the user turned; its
            result is saved only on request, beside the file.
        checks: results of `check` (``check-lattice``), for ``--stats``.
    """

    volume: volumes.Volume
    drawing: Drawing
    state: ViewerState
    options: Options
    static_lattice: HeldLattice | None
    static_file: LatticeOnFile | None

    def __init__(self, volume: volumes.Volume, drawing: Drawing, state: ViewerState,
                 options: Options) -> None:
        self.volume, self.drawing, self.state, self.options = volume, drawing, state, options
        self.shared: SharedLattice | None = None
        self.bake: BakeLink | None = None
        self.static_lattice = self.static_file = None
        self.relit_file: bool = False
        self.checks: list[dict[str, Any]] = []
        self._view_sent: tuple | None = None
        self._view_seen: tuple | None = None
        self._view_since = 0.0
        self._gi_upload: tuple | None = None  # (iso, uploader, bricks watched: `gi_shown`)

    # -- starting ------------------------------------------------------------------------
    def start(self, lattice: LatticeOnFile | None, iso: float) -> None:
        """Show `lattice` (a lattice file opened, `baking.view_texels.LatticeOnFile`, or
        None) and start the lazy bake when it is missing or incomplete (unless
        ``--no-bake``, or the file's texels are not those a bake places: it is shown as it
        is, and the status line says why, `baking.lattice.other_texels`)."""
        from isolume.baking.config import BakeConfig
        from isolume.baking.lattice import other_texels

        config = None
        if lattice is not None:
            config = lattice.config
            self.drawing.albedo = tuple(config.albedo)
            other = other_texels(lattice.geometry, self.volume, config.scale, lattice.file.path)
            if not self.options.bake or _complete(lattice, config.samples) or other:
                self.state.message = other or self.state.message
                self.static_file, self.static_lattice = lattice, lattice.held(fill=True)
                self._show(self.static_lattice)
                return
        if not self.options.bake:
            return
        if config is None:
            config = BakeConfig(mode=self.options.bake_mode, env=self.options.bake_env,
                                samples=self.options.bake_samples,
                                max_levels=self.options.bake_max_levels)
        self._start_bake(lattice, config, iso)

    def _start_bake(self, lattice, config, iso: float) -> None:
        """Show the lattice of the file `lattice` (a `LatticeOnFile`; None: a new one for
        `config`) from shared memory and start its lazy bake with `config`."""
        from isolume.baking.lattice import LatticeGeometry

        geometry = LatticeGeometry.for_volume(self.volume, config.scale)
        meta = lattice.meta if lattice is not None else lattice_meta(self.volume, config)
        self.shared = SharedLattice.create(geometry, meta["channels"], meta, lattice)
        self.static_lattice = None
        if self._show(self.shared.lattice):
            self.drawing.track_uploads()
        self.bake = BakeLink(self.volume, config, self.shared, self.options.bake_workers, iso,
                             follow_iso=lattice is None)

    def _show(self, lattice) -> bool:
        problem = self.drawing.show_lattice(lattice)
        if problem is not None:
            self.state.message = problem
        return problem is None

    # -- every turn of the loop ----------------------------------------------------------
    def receive(self) -> None:
        """Upload the texels the bake committed (for `UPLOAD_BUDGET_S` a turn, the bricks'
        first light for `UPLOAD_FIRST_S` while the view rests); note its error as the
        status message."""
        if self.bake is None:
            return
        for ids in self.bake.poll():
            self.drawing.mark_texels(ids)
        if self.bake.error:
            self.state.message = f"lazy bake stopped: {self.bake.error}"
        resting = not self.state.interacting(time.perf_counter())
        first = UPLOAD_FIRST_S if resting else None
        if self.drawing.upload_texels(UPLOAD_BUDGET_S, first) \
                and self.state.view.shading in lattice_modes():
            self.state.lattice_changed = True  # shown by the loop, at a pace

    def update_view(self, surface_stage: str | None, size: tuple[int, int]) -> None:
        """Tell the bake process what is on screen, and what a screenshot of it shows
        (`_shown_points`), once the view has settled.

        Args:
            surface_stage: the stage ("coarse", "full") of the surface on screen when it
                is the requested isovalue's, else None.
            size: (W, H) pixels of the frame.
        """
        if self.bake is None and self.static_lattice is not None:
            self._bake_turned_file()
        if self.bake is None or surface_stage is None:
            return
        state = self.state
        turned = self.drawing.turned_light(state.view)  # its bounced light follows it
        key = (state.view.iso, state.camera, surface_stage == "full",
               None if turned is None else turned[1])
        now = time.perf_counter()
        if key != self._view_seen:  # the view changed: wait until it holds still
            self._view_seen, self._view_since = key, now
            return
        if key == self._view_sent or now - self._view_since < SETTLE_S or state.drag is not None:
            return
        from isolume.baking.lazy import View, visible_cells

        points = self._shown_points(size)
        cells = visible_cells(self.shared.lattice.geometry, points)
        self.bake.send_view(View(state.view.iso, tuple(float(v) for v in state.camera.eye),
                                 cells, key[3], points.astype("float32")))
        self._view_sent = key

    def _shown_points(self, size: tuple[int, int]) -> np.ndarray:
        """(N, 3) world positions of the surface under the window's pixels (those under
        the panel included) and under a screenshot's (`ViewerState.whole_window`, whose
        eye stands beside the window's while the panel keeps the picture aside: it sees
        faces turned from the window's eye).

        Args:
            size: (W, H) pixels of the frame.
        """
        state, whole = self.state, self.state.whole_window()
        cameras = [state.camera] if whole == state.camera else [state.camera, whole]
        return np.concatenate([self.drawing.visible_points(camera, state.view, size)
                               for camera in cameras])

    def _bake_turned_file(self) -> None:
        """A complete lattice from a file whose sun (or light) the user turned: start a
        lazy bake with the file's config, which re-bakes the bounced light for the turned
        light around the view. Its result is saved only on request, beside the file
        (`app.viewer.saving.Saver.save_lattice`): the file keeps its whole bake."""
        turned = self.drawing.turned_light(self.state.view)
        if self.state.drag is not None or not self._file_turned(turned):
            return
        self.relit_file = True
        self._start_bake(self.static_file, self.static_lattice.config, self.state.view.iso)

    # -- pausing -------------------------------------------------------------------------
    def pause(self, paused: bool) -> None:
        """Pause (True) or resume the lazy bake, if one runs."""
        if self.bake is not None:
            self.bake.pause(paused)

    def toggle_pause(self) -> None:
        """Pause the lazy bake if it runs, resume it if it is paused."""
        if self.bake is not None:
            self.bake.pause(not self.bake.paused)

    def hold(self, held: bool) -> None:
        """Pause (True) or resume the lazy bake, if one runs; `held` says when the process
        has stopped writing."""
        if self.bake is not None:
            if held:
                self.bake.paused_ack = False
            self.bake.pause(held)

    def held(self) -> bool:
        """No lazy bake writes texels now (none runs, or it acknowledged a pause)."""
        return self.bake is None or self.bake.paused_ack

    # -- questions -----------------------------------------------------------------------
    def gi_shown(self) -> bool:
        """Whether global illumination of the displayed isovalue is on screen: a lattice
        shown without a lazy bake, or the lazy bake's first preview pass of that isovalue
        (or estimates of every visible texel) received, and the texels received by then
        uploaded to GL (they go up a few bricks a frame, `TexelUploader.watch`)."""
        if self.bake is None:
            return self.drawing.renderer.lattice is not None
        iso, uploader = self.state.view.iso, self.drawing.uploader
        if not self.bake.gi_received(iso):
            return False
        if uploader is None:
            return True
        if self._gi_upload is None or self._gi_upload[:2] != (iso, uploader):
            self._gi_upload = (iso, uploader, uploader.watch())  # what came by now
        return not self._gi_upload[2].any()

    def bake_progress(self) -> tuple[float | None, str | None]:
        """(fraction of the texels near the displayed surface with samples of their own in
        the lattice baked — a turned light's after a turn, what `save_lattice` writes —,
        None before the bake reports on this isovalue under the light as turned now; the
        bake's error or None).

        Raises:
            ViewerError: no lazy bake runs, nor will one for a turned light.
        """
        turned = self.drawing.turned_light(self.state.view)
        if self.bake is None and self._file_turned(turned):
            return None, None  # its bake starts once the light rests turned
        if self.bake is None:
            raise ViewerError("no lazy bake is running (--no-bake, or the lattice is "
                              "complete)")
        if turned is not None and not self.bake.on_light(turned[1]):
            return None, self.bake.error  # not (yet) baking under the light as turned
        return self.bake.near_fraction(self.state.view.iso), self.bake.error

    def _file_turned(self, turned: tuple[str, tuple[float, ...]] | None) -> bool:
        """Whether a complete lattice file is shown, to be re-baked (`_rebakes_file`) for
        the light `turned` (`Drawing.turned_light`) away from the one it was baked with."""
        from isolume.baking.lazy import same_direction, turned_light

        return (turned is not None and self._rebakes_file()
                and not same_direction(turned[1], turned_light(self.static_lattice.config)))

    def _rebakes_file(self) -> bool:
        """Whether a lattice file shown as is gets a lazy bake of its turned light
        (`_bake_turned_file`): baking is on and its texels are those a bake places."""
        from isolume.baking.lattice import other_texels

        if self.static_lattice is None or not self.options.bake:
            return False
        return not other_texels(self.static_file.geometry, self.volume,
                                self.static_lattice.config.scale)

    def relit_progress(self) -> tuple[float | None, str | None]:
        """(share of the visible texels showing the bounced light of the light as turned
        now, None before the bake reports on it; the bake's error or None).

        Raises:
            ViewerError: no lazy bake runs, or no light is shaded per pixel.
        """
        from isolume.baking.lazy import same_direction, turned_light

        turned = self.drawing.turned_light(self.state.view)
        file = self.static_lattice is not None and self.options.bake
        if turned is None or (self.bake is None and not file):
            raise ViewerError("no lazy bake of a per-pixel sun or light to wait for "
                              "(mode irradiance with a lattice that --no-bake leaves as is)")
        if self.bake is None:  # a complete file: its bake starts once the light rests turned
            baked = turned_light(self.static_lattice.config)
            return (1.0 if same_direction(turned[1], baked) else None), None
        return self.bake.relit_fraction(turned[1]), self.bake.error

    def check(self) -> dict[str, Any]:
        """Upload what is pending, compare the GL textures with the lattice
        (`app.viewer.draw.check_textures`), note and print the result.

        Raises:
            ViewerError: no lattice is shown.
        """
        if self.drawing.renderer.lattice is None:
            raise ViewerError("no lattice is shown")
        self.receive()  # texels committed before a pause took effect
        result = self.drawing.check_lattice()
        self.checks.append(result)
        print(f"isolume: check-lattice: {json.dumps(result)}")
        return result

    def light_note(self) -> str:
        """The panel's line under the light controls: what turning the light does."""
        view = self.state.view
        if view.shading == "sh":
            return "The light controls rotate the environment (SH transfer)."
        if self.drawing.light_note(view) is not None:  # sun/lights per pixel
            return self._relit_line() or self.drawing.light_note(
                view, rebakes=self.bake is not None or self._rebakes_file())
        if view.shading in lattice_modes():
            return ("The light is baked into the lattice (fixed); rotating it moves "
                    "only the fallback light of texels not computed yet.")
        return ""

    def _relit_line(self) -> str | None:
        """The lazy bake's progress on the bounced light of the light as turned (None
        before it starts on it)."""
        turned = self.drawing.turned_light(self.state.view)
        if self.bake is None or turned is None:
            return None
        return self.bake.relit_line(turned[1], turned[0])

    def status(self) -> tuple[tuple[float, float] | None, tuple[str, ...]]:
        """The panel's bake section: ((visible, surface) shares with samples of their own,
        or None; status lines)."""
        iso = self.state.view.iso
        if self.bake is None:
            if self.static_lattice is not None:
                return None, (*range_warning(self.static_lattice.meta, iso),
                              "lattice loaded (complete)")
            return None, ()
        return self.bake.status(iso)

    @property
    def paused(self) -> bool:
        """A lazy bake runs and is paused."""
        return bool(self.bake and self.bake.paused)

    def relight_pending(self) -> bool:
        """A lattice file's lazy bake for a turned light is started, and the bake process
        has not begun on that light yet: the lattice in shared memory is still the
        file's."""
        return self.relit_file and self.bake is not None and self.bake.relit_config is None

    def snapshot(self) -> Lattice | None:
        """A `baking.lattice.Lattice` copy of the lattice being baked, to save (None: no
        lazy bake started)."""
        if self.shared is None:
            return None
        return (self.bake.snapshot(self.shared) if self.bake is not None
                else self.shared.snapshot())

    def figures(self) -> dict[str, Any] | None:
        """The lazy bake's part of ``--stats`` (None: no lazy bake ran)."""
        if self.bake is None:
            return None
        uploader = self.drawing.uploader
        p = self.bake.progress
        return {"ready": {k: v for k, v in (self.bake.ready or {}).items() if k != "meta"},
                "progress": asdict(p) if p is not None else None,
                "previews": [{"at_s": at, **f} for at, f in self.bake.previews],
                "stats": self.bake.stats, "error": self.bake.error,
                "turns": [{k: v for k, v in t.items() if k != "sent"}
                          for t in self.bake.turns],
                "blocks_uploaded": uploader.uploaded if uploader else 0}

    # -- the end -------------------------------------------------------------------------
    def stop(self) -> None:
        """Stop the lazy-bake process (the shared lattice stays readable until `close`)."""
        if self.bake is not None:
            self.bake.stop()

    def close(self) -> None:
        """Free the shared lattice."""
        if self.shared is not None:
            self.shared.close()

