"""Vertex colours and the mesh files of ``isolume export``: glTF binary (.glb) and PLY.

Colours go as ``isolume render``'s pixels go (``shaders/tonemap.frag``): the linear
radiance times the exposure, through the tone curve (`tone`), to a display value in
[0, 1]. glTF defines COLOR_0 as linear: it gets that display value itself (what the
picture's sRGB encoding starts from), as float32; PLY gets it sRGB-encoded to 8 bits (the
PNG's bytes). The unexposed linear radiance goes beside it, float32: glTF ``_RADIANCE``
(an application-specific attribute: glTF allows those with a leading underscore), PLY
``radiance_r``, ``radiance_g``, ``radiance_b``.

glTF is +Y up: positions and normals turn from isolume's +Z up, (x, y, z) → (x, z, −y)
(Blender's importer turns them back); one world unit is written as one glTF metre. The
material is white, double-sided and unlit (KHR_materials_unlit): a viewer shows COLOR_0 as
it is, lighting nothing again on top of the light it holds. PLY keeps isolume's world
coordinates (+Z up), binary little-endian, with normals ``nx ny nz``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from isolume import volumes
from isolume.volumes.writing import atomic_write

SUFFIXES = (".glb", ".ply")
"""The mesh files ``isolume export`` writes."""
Z_UP_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
"""(3, 3) world (+Z up) → glTF (+Y up): a turn of −90° about x."""
UNLIT = "KHR_materials_unlit"
_FLOAT, _UINT32 = 5126, 5125  # glTF accessor component types
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963  # glTF buffer view targets


def tone(x: np.ndarray, curve: str) -> np.ndarray:
    """(…, 3) display values in [0, 1] of exposed linear radiance `x` under the tone
    `curve` ("clamp", "reinhard" or "aces": `app.render.settings.TONEMAPS`, the curves of
    ``tonemap.frag``: clamp to [0, 1]; x / (1 + x); Narkowicz's ACES fit, clamped)."""
    x = np.maximum(np.asarray(x, np.float64), 0.0)
    if curve == "reinhard":
        return x / (1.0 + x)
    if curve == "aces":
        return np.clip(x * (2.51 * x + 0.03) / (x * (2.43 * x + 0.59) + 0.14), 0.0, 1.0)
    if curve == "clamp":
        return np.clip(x, 0.0, 1.0)
    raise ValueError(f"unknown tone curve {curve!r}")


def srgb_bytes(display: np.ndarray) -> np.ndarray:
    """(…, 3) uint8 sRGB encoding of linear display values in [0, 1] (``srgb_encode`` of
    ``tonemap.frag``, rounded)."""
    c = np.clip(np.asarray(display, np.float64), 0.0, 1.0)
    encoded = np.where(c < 0.0031308, 12.92 * c, 1.055 * c ** (1 / 2.4) - 0.055)
    return np.round(encoded * 255).astype(np.uint8)


def vertex_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V,) a third of the area of the triangles around each vertex (world units²), the
    part of the surface each vertex's colour covers: the automatic exposure's weights."""
    v = np.asarray(vertices, np.float64)
    a, b, c = (v[faces[:, k]] for k in range(3))
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    out = np.zeros(len(v))
    for k in range(3):
        np.add.at(out, faces[:, k], area / 3)
    return out


def write_mesh(path: Path, mesh: volumes.Mesh, display: np.ndarray, radiance: np.ndarray,
               extras: dict[str, Any]) -> None:
    """Write `mesh` with its (V, 3) `display` colours (linear, in [0, 1]) and (V, 3)
    linear `radiance` to `path` (.glb or .ply); `extras` (JSON-ready) describes how they
    were made (glTF: the asset's extras; PLY: comments), whole or not at all
    (`volumes.writing.atomic_write`)."""
    write = write_glb if path.suffix.lower() == ".glb" else write_ply
    atomic_write(path, lambda tmp: write(Path(tmp), mesh, display, radiance, extras), "mesh")


def write_glb(path: Path, mesh: volumes.Mesh, display: np.ndarray, radiance: np.ndarray,
              extras: dict[str, Any]) -> None:
    """glTF 2.0 binary: one mesh of POSITION, NORMAL, COLOR_0 (linear display colour) and
    ``_RADIANCE`` (linear radiance), float32 VEC3 each, uint32 indices, one unlit
    material (module docs)."""
    import pygltflib as gltf

    positions = (np.asarray(mesh.vertices, np.float64) @ Z_UP_TO_Y_UP.T).astype(np.float32)
    normals = (np.asarray(mesh.normals, np.float64) @ Z_UP_TO_Y_UP.T).astype(np.float32)
    blob = bytearray()
    views, accessors = [], []
    columns = {"indices": np.ascontiguousarray(mesh.faces, np.uint32).reshape(-1),
               "POSITION": positions, "NORMAL": normals,
               "COLOR_0": np.asarray(display, np.float32),
               "_RADIANCE": np.asarray(radiance, np.float32)}
    for name, data in columns.items():
        index = name == "indices"
        views.append(gltf.BufferView(buffer=0, byteOffset=len(blob), byteLength=data.nbytes,
                                     target=_ELEMENT_ARRAY_BUFFER if index else _ARRAY_BUFFER))
        blob += np.ascontiguousarray(data).tobytes()  # 4-byte items: stays aligned
        accessors.append(gltf.Accessor(
            bufferView=len(views) - 1, componentType=_UINT32 if index else _FLOAT,
            count=len(data), type="SCALAR" if index else "VEC3",
            min=data.min(axis=0).tolist() if name == "POSITION" else None,
            max=data.max(axis=0).tolist() if name == "POSITION" else None))
    attributes = gltf.Attributes(**{name: k for k, name in enumerate(columns) if k > 0})
    material = gltf.Material(
        name="isolume baked light (unlit)", doubleSided=True, extensions={UNLIT: {}},
        pbrMetallicRoughness=gltf.PbrMetallicRoughness(baseColorFactor=[1.0, 1.0, 1.0, 1.0],
                                                       metallicFactor=0.0,
                                                       roughnessFactor=1.0))
    document = gltf.GLTF2(
        asset=gltf.Asset(generator="isolume export", version="2.0", extras=extras),
        extensionsUsed=[UNLIT], scene=0, scenes=[gltf.Scene(nodes=[0])],
        nodes=[gltf.Node(mesh=0, name=extras.get("volume", "isosurface"))],
        meshes=[gltf.Mesh(name="isosurface", primitives=[
            gltf.Primitive(attributes=attributes, indices=0, material=0)])],
        materials=[material], accessors=accessors, bufferViews=views,
        buffers=[gltf.Buffer(byteLength=len(blob))])
    document.set_binary_blob(bytes(blob))
    document.save_binary(str(path))


def write_ply(path: Path, mesh: volumes.Mesh, display: np.ndarray, radiance: np.ndarray,
              extras: dict[str, Any]) -> None:
    """Binary PLY (trimesh): vertices, normals ``nx ny nz``, 8-bit sRGB colours ``red
    green blue alpha``, float ``radiance_r radiance_g radiance_b``; `extras` as comments."""
    import trimesh

    colours = np.concatenate([srgb_bytes(display),
                              np.full((len(display), 1), 255, np.uint8)], axis=1)
    shape = trimesh.Trimesh(vertices=mesh.vertices, faces=mesh.faces,
                            vertex_normals=mesh.normals, vertex_colors=colours, process=False)
    for c, channel in enumerate("rgb"):
        shape.vertex_attributes[f"radiance_{channel}"] = np.asarray(radiance[:, c], np.float32)
    text = trimesh.exchange.ply.export_ply(shape, encoding="binary", vertex_normal=True)
    comments = "".join(f"comment {key} {value}\n" for key, value in extras.items())
    head, _, body = text.partition(b"\nelement vertex")
    path.write_bytes(head + b"\n" + comments.encode() + b"element vertex" + body)
