"""Between napari's layers and isolume's volumes, meshes, colours and saved views.

napari indexes an Image layer's data (z, y, x), as isolume does, and gives its `scale`
and `translate` per axis in that order; isolume's spacing and origin are (x, y, z), so
they are the reversed vectors (`layer_volume`), and the world position of data index
(k, j, i) is the same in both: translate + (k, j, i) · scale. The plugin lights the
isosurface in that frame, then hands napari the vertices as data indices (z, y, x)
(`data_vertices`) with the Image layer's own scale, translate, rotate, shear and affine
(`layer_transform`): the Surface layer overlays the Image exactly under any of them; a
rotation, shear or affine turns the lit surface, with its light, as it turns the image.

Nothing here imports Qt; napari's layer and camera objects are read through their
attributes only.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from isolume import volumes
from isolume.volumes.errors import IsolumeError

if TYPE_CHECKING:
    import napari

    from isolume.app.render.camera import Camera

TONE_CURVE = "aces"
"""The tone curve of `render`'s and `export`'s default, which the colours go through."""
DEFAULT_FOV = 30.0
"""Vertical field of view (degrees) of a saved view whose napari camera is orthographic."""


class NapariLayerError(IsolumeError):
    """An Image layer the plugin cannot light; the message says why."""


def layer_volume(layer: object) -> volumes.Volume:
    """The `Volume` of a napari Image `layer`: its data (the full-resolution level of a
    multiscale image) with spacing and origin (x, y, z) from the layer's (z, y, x) scale
    and translate.

    Raises:
        NapariLayerError: not an Image layer, an RGB(A) image, not 3-D, a scale that is
            not positive, or data that `volumes.Volume` refuses (one line).
    """
    from napari.layers import Image

    name = getattr(layer, "name", "layer")
    if not isinstance(layer, Image):
        raise NapariLayerError(f"{name}: expected an Image layer, got a "
                               f"{type(layer).__name__} layer")
    if layer.rgb:
        raise NapariLayerError(f"{name}: an RGB(A) image has no scalar isosurface; "
                               "use a single-channel 3-D image")
    data = layer.data[0] if layer.multiscale else layer.data
    if layer.ndim != 3:
        raise NapariLayerError(f"{name}: expected a 3-D image (z, y, x), got "
                               f"{layer.ndim} dimensions of shape {tuple(data.shape)}")
    scale = np.asarray(layer.scale, np.float64)
    if not (scale > 0).all():
        raise NapariLayerError(f"{name}: scale {tuple(float(s) for s in scale)} must be "
                               "positive along z, y and x")
    try:
        return volumes.Volume(np.asarray(data), spacing=tuple(scale[::-1]),
                              origin=tuple(np.asarray(layer.translate, np.float64)[::-1]),
                              name=name, source=f"napari layer {name}")
    except volumes.VolumeError as exc:
        raise NapariLayerError(str(exc)) from None


def layer_transform(layer: napari.layers.Image) -> dict[str, np.ndarray]:
    """The keywords that give a Surface layer the Image `layer`'s placement in the world:
    its scale, translate, rotate, shear and affine (arrays, napari's (z, y, x) order)."""
    return {"scale": np.asarray(layer.scale), "translate": np.asarray(layer.translate),
            "rotate": np.asarray(layer.rotate), "shear": np.asarray(layer.shear),
            "affine": np.asarray(layer.affine.affine_matrix)}


def data_vertices(volume: volumes.Volume, vertices: np.ndarray) -> np.ndarray:
    """(V, 3) float32 data indices (z, y, x) of (V, 3) world vertices (x, y, z) of
    `volume`: what a Surface layer with the Image layer's transform (`layer_transform`)
    draws where the Image draws that point."""
    return volume.world_to_index(vertices).astype(np.float32)


def display_colours(radiance: np.ndarray, areas: np.ndarray, exposure: float,
                    auto: bool = True) -> tuple[np.ndarray, float]:
    """((V, 3) float32 vertex colours in [0, 1], sRGB-encoded as a screen shows them; the
    linear exposure used): (V, 3) linear `radiance` times `exposure` (times the
    automatic exposure with `auto`: the log-average luminance of the surface, its
    vertices weighted by their (V,) `areas`, to middle grey), through `TONE_CURVE`, as
    ``isolume export`` colours its vertices (the bytes of its PLY, over 255)."""
    from isolume.app.export_files import srgb_bytes, tone
    from isolume.app.render.exposure import auto_exposure_scale

    radiance = np.asarray(radiance, np.float64)
    if auto:
        exposure *= auto_exposure_scale(radiance, np.ones(len(radiance), bool),
                                        weights=areas)
    colours = srgb_bytes(tone(radiance * exposure, TONE_CURVE)) / np.float32(255)
    return colours.astype(np.float32), float(exposure)


def direction_from_angles(azimuth: float, elevation: float) -> np.ndarray:
    """(3,) unit vector (x, y, z) of a direction at `azimuth` degrees from +x towards +y
    and `elevation` degrees above the x-y plane (the sky's ``sun_az``, ``sun_el``)."""
    az, el = np.radians(azimuth), np.radians(elevation)
    return np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


def angles_of(direction: Sequence[float] | np.ndarray) -> tuple[float, float]:
    """(azimuth, elevation) degrees of a (3,) direction (x, y, z): the inverse of
    `direction_from_angles`."""
    d = np.asarray(direction, np.float64)
    d = d / np.linalg.norm(d)
    return (float(np.degrees(np.arctan2(d[1], d[0]))),
            float(np.degrees(np.arcsin(np.clip(d[2], -1.0, 1.0)))))


def world_to_volume(layer: napari.layers.Image, volume: volumes.Volume,
                    world: Sequence[float] | np.ndarray) -> np.ndarray:
    """(3,) volume world position (x, y, z) of the napari world point `world` (the
    layer's dimensions, (z, y, x)), through the layer's whole transform."""
    index = np.asarray(layer.world_to_data(tuple(float(v) for v in world)), np.float64)
    return volume.index_to_world(index[None, -3:])[0]


def orthographic_distance(local: np.ndarray, plain: float) -> float:
    """Distance (world units) from the centre of an orthographic view of a perspective
    camera looking the same way that shows the points at `local` as large as the
    orthographic view does: none farther from the picture's middle, the one that lands
    farthest as far.

    At `plain` (half the view's height / tan(half the field of view)) the two match only
    in the plane through the centre: a point `near` world units in front of it (towards
    the eye), `across` from the line of sight, lands at across · plain / (d - near) at
    distance d, larger than in the orthographic view (a cube filling napari's view by
    about 1.3×). It lands no farther than the farthest point's reach R there for
    d ≥ near + plain · across / R: the distance is the largest of these (`plain` without
    points).

    Args:
        local: (N, 3) the points from the view's centre along its right, up and back
            (towards the eye) directions, world units.
    """
    if len(local) == 0:
        return float(plain)
    across = np.hypot(local[:, 0], local[:, 1])
    reach = across.max()
    share = across / reach if reach > 0 else np.ones_like(across)
    return float((local[:, 2] + plain * share).max())


def _shown_points(points: np.ndarray, target: np.ndarray, forward: np.ndarray,
                  up: np.ndarray, half: float, aspect: float) -> np.ndarray:
    """(K, 3) the world `points` (N, 3) that a view centred on `target`, looking along
    the unit `forward`, `up` (world, not yet square to `forward`) above it and `half`
    world units from the centre to the top of a picture `aspect` (width / height) wide,
    shows: each along the view's right, up and back (towards the eye) directions."""
    up = up - (up @ forward) * forward
    up = up / np.linalg.norm(up)
    local = (np.asarray(points, np.float64) - target) @ np.stack(
        [np.cross(forward, up), up, -forward], axis=1)
    return local[(np.abs(local[:, 0]) <= half * aspect) & (np.abs(local[:, 1]) <= half)]


def saved_camera(layer: napari.layers.Image, volume: volumes.Volume,
                 camera: napari.components.Camera, canvas: tuple[int, int],
                 points: np.ndarray) -> Camera:
    """The `app.render.camera.Camera` of napari's 3-D `camera` (its centre, view
    direction, zoom and perspective) in `volume`'s world, for a picture of napari's
    (height, width) `canvas` pixels: looking along the same direction at the same
    centre. napari's perspective camera keeps its field of view and distance; its
    orthographic camera becomes a `DEFAULT_FOV` perspective one that shows the (N, 3)
    world `points` (the surface's) on the canvas as large as napari does
    (`orthographic_distance`). isolume's camera keeps +z up: a view rolled about its
    direction in napari is saved unrolled.

    Args:
        layer: the Image layer lit (its transform maps napari's world to the volume's).
        camera: ``viewer.camera`` (centre and directions in world (z, y, x)).
    """
    from isolume.app.render.camera import Camera

    centre = np.asarray(camera.center, np.float64)
    target = world_to_volume(layer, volume, centre)
    ahead = world_to_volume(layer, volume, centre + np.asarray(camera.view_direction))
    forward = (ahead - target) / np.linalg.norm(ahead - target)
    height, width = canvas
    top = centre + 0.5 * height / camera.zoom * np.asarray(camera.up_direction)
    up = world_to_volume(layer, volume, top) - target
    half = float(np.linalg.norm(up))  # world units from the centre to the top
    fov = float(camera.perspective) or DEFAULT_FOV
    distance = half / np.tan(np.radians(fov) / 2)  # a perspective camera's own
    if not camera.perspective:
        shown = _shown_points(points, target, forward, up, half, width / height)
        distance = orthographic_distance(shown, distance)
    scale = volume.diagonal or 1.0
    azimuth = float(np.degrees(np.arctan2(-forward[0], forward[1])))
    elevation = float(np.degrees(np.arcsin(np.clip(-forward[2], -1.0, 1.0))))
    return Camera(azimuth=azimuth, elevation=elevation, distance=distance / scale,
                  target=tuple(float(v) for v in target), scale=scale, fov_y=fov)


def write_volume(volume: volumes.Volume, path: str | os.PathLike[str]) -> None:
    """`volume` as a ``.npz`` that isolume reads back as it is (``data`` (Z, Y, X),
    ``spacing`` and ``origin`` (x, y, z))."""
    np.savez(path, data=volume.data, spacing=np.asarray(volume.spacing),
             origin=np.asarray(volume.origin))
