"""Orbit camera: view and projection matrices (column vectors, OpenGL clip space).

``--view AZ,EL[,DIST]``: azimuth and elevation in degrees around the centre of the volume,
distance in units of the volume's diagonal. World up is +z. Azimuth 0 looks from −y
towards +y; positive azimuth turns the eye counter-clockwise seen from above.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np


@dataclass(frozen=True)
class Camera:
    """A perspective orbit camera.

    Attributes:
        azimuth, elevation: degrees.
        distance: eye distance from the target, in units of `scale` (the volume diagonal).
        target: (3,) world point looked at.
        scale: world length of one distance unit.
        fov_y: vertical field of view, degrees.
        pan: (2,) offset of the target in the view plane, in units of `scale`.
    """

    azimuth: float = 30.0
    elevation: float = 30.0
    distance: float = 1.8
    target: tuple[float, float, float] = (0.0, 0.0, 0.0)
    scale: float = 1.0
    fov_y: float = 30.0
    pan: tuple[float, float] = (0.0, 0.0)

    def _basis(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(forward, right, up) unit vectors of the view."""
        az, el = np.radians(self.azimuth), np.radians(self.elevation)
        back = np.array([np.cos(el) * np.sin(az), -np.cos(el) * np.cos(az), np.sin(el)])
        forward = -back
        right = np.cross(forward, (0.0, 0.0, 1.0))
        if np.linalg.norm(right) < 1e-9:  # looking straight up or down
            right = np.array([np.cos(az), np.sin(az), 0.0])
        right /= np.linalg.norm(right)
        up = np.cross(right, forward)
        return forward, right, up

    @property
    def center(self) -> np.ndarray:
        """(3,) the orbit centre including pan, world units."""
        _, right, up = self._basis()
        return np.asarray(self.target) + self.scale * (self.pan[0] * right + self.pan[1] * up)

    @property
    def eye(self) -> np.ndarray:
        """(3,) eye position, world units."""
        forward, _, _ = self._basis()
        return self.center - forward * self.distance * self.scale

    def view_matrix(self) -> np.ndarray:
        """(4, 4) world → eye transform."""
        forward, right, up = self._basis()
        m = np.eye(4)
        m[0, :3], m[1, :3], m[2, :3] = right, up, -forward
        m[:3, 3] = -m[:3, :3] @ self.eye
        return m

    def clip_range(self) -> tuple[float, float]:
        """(near, far) planes that enclose a sphere of radius `scale` around the target."""
        d = self.distance * self.scale
        far = d + 1.5 * self.scale
        return max(far * 1e-4, d - 1.5 * self.scale), far

    def projection_matrix(self, aspect: float) -> np.ndarray:
        """(4, 4) perspective projection for width/height `aspect`."""
        near, far = self.clip_range()
        f = 1.0 / np.tan(np.radians(self.fov_y) / 2)
        m = np.zeros((4, 4))
        m[0, 0], m[1, 1] = f / aspect, f
        m[2, 2] = (far + near) / (near - far)
        m[2, 3] = 2 * far * near / (near - far)
        m[3, 2] = -1.0
        return m

    def view_proj(self, aspect: float) -> np.ndarray:
        """(4, 4) world → clip transform."""
        return self.projection_matrix(aspect) @ self.view_matrix()

    def primary_rays(self, width: int, height: int, pixels: np.ndarray | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
        """Rays through pixel centres, row 0 at the top: of every pixel, or of the (M,)
        flat indices `pixels` only (the same bits as those rows of every pixel's).

        Returns:
            origins: (M, 3) the eye, repeated; directions: (M, 3) unit vectors (M = H*W
            for every pixel).
        """
        forward, right, up = self._basis()
        t = np.tan(np.radians(self.fov_y) / 2)
        aspect = width / height
        xs = ((np.arange(width) + 0.5) / width * 2 - 1) * t * aspect
        ys = (1 - (np.arange(height) + 0.5) / height * 2) * t
        if pixels is None:
            gx, gy = (grid.reshape(-1) for grid in np.meshgrid(xs, ys))
        else:
            rows, columns = np.divmod(np.asarray(pixels, np.int64), width)
            gx, gy = xs[columns], ys[rows]
        d = forward + gx[:, None] * right + gy[:, None] * up
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return np.broadcast_to(self.eye, d.shape).copy(), d


def parse_view(text: str) -> tuple[float, float, float | None]:
    """Parse ``AZ,EL[,DIST]`` (degrees, degrees, diagonals) → (az, el, dist or None)."""
    parts = text.split(",")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise ValueError(f"--view {text!r}: expected AZ,EL[,DIST] as numbers") from None
    if len(values) not in (2, 3) or not np.isfinite(values).all():
        raise ValueError(f"--view {text!r}: expected AZ,EL[,DIST] (two or three numbers)")
    if len(values) == 3 and values[2] <= 0:
        raise ValueError(f"--view {text!r}: DIST must be positive, got {values[2]:g}")
    if abs(values[1]) > 90:
        raise ValueError(f"--view {text!r}: elevation must lie in [-90, 90], got {values[1]:g}")
    return values[0], values[1], values[2] if len(values) == 3 else None


FRAME_FILL = 0.9
"""Framing brings the points' projections within this fraction of the free part's
half-width or half-height, whichever binds."""
FRAME_OUTLIERS = 0.001
"""Framing leaves out this fraction of the points on each side (specks of noise far from
the object; what lies just past it stays within the margin that `FRAME_FILL` leaves).
Sets of under a thousand points (a box's corners) are framed whole."""


def frame_points(camera: Camera, points: np.ndarray, aspect: float,
                 free: tuple[float, float] = (0.0, 1.0), centre: bool = False) -> Camera:
    """`camera` (its azimuth, elevation and field of view) aimed at the (N, 3) world
    `points` (a surface's, or a box's corners) so that their projections fill
    `FRAME_FILL` of the free part of the picture (its width or its height, whichever
    binds).

    Args:
        aspect: width / height of the picture.
        free: (left, right) edges of the free part, fractions of the width (what a panel
            on the left leaves: (panel's right edge / width, 1)).
        centre: also pan so that the projections' extent sits in the middle of the free
            part (a still picture); False: the points' box centre sits there, so that
            orbiting turns the surface about the middle (the viewer, a turntable).

    Returns:
        A camera whose target is the points' box centre, whose `scale` is that box's
        diagonal and whose `pan` shifts the picture as asked (the pan turns with the view).
    """
    points = np.asarray(points, np.float64)
    lo, hi = points.min(axis=0), points.max(axis=0)
    scale = max(float(np.linalg.norm(hi - lo)), 1e-9)
    t = np.tan(np.radians(camera.fov_y) / 2)
    left, right = free
    width, middle = right - left, left + right - 1.0  # of the free part, in NDC x
    # start where the bounding sphere fits, then move in until the points fill the part
    half = FRAME_FILL * min(t, t * aspect * width)
    distance = 0.5 * scale / np.sin(np.arctan(half))
    shift = np.array([-middle, 0.0])  # NDC offset of the target from the picture's middle
    framed = camera
    for _ in range(16):
        framed = replace(camera, target=tuple((lo + hi) / 2), scale=scale,
                         distance=float(distance / scale),
                         pan=(float(shift[0] * t * aspect * distance / scale),
                              float(shift[1] * t * distance / scale)))
        ndc = _project(framed, aspect, points)
        if centre:
            low = np.quantile(ndc, FRAME_OUTLIERS, axis=0, method="lower")
            high = np.quantile(ndc, 1 - FRAME_OUTLIERS, axis=0, method="higher")
            off = (low + high) / 2 - (middle, 0.0)
            shift += off
            fill = max((high[0] - low[0]) / width, high[1] - low[1]) / 2 / FRAME_FILL
        else:
            off = np.zeros(2)
            reach = np.quantile(np.abs(ndc - (middle, 0.0)), 1 - FRAME_OUTLIERS, axis=0,
                                method="higher")
            fill = max(reach[0] / width, reach[1]) / FRAME_FILL
        if abs(fill - 1.0) < 1e-3 and np.abs(off).max() < 1e-3:
            break
        # a distant set's projection shrinks as 1/distance; about the centre, by less
        distance *= 1.0 + 0.9 * (fill - 1.0)
    return framed


def _project(camera: Camera, aspect: float, points: np.ndarray) -> np.ndarray:
    """(N, 2) normalised device coordinates of (N, 3) world points."""
    p = np.c_[points, np.ones(len(points))] @ camera.view_proj(aspect).T
    return p[:, :2] / p[:, 3:]
