"""HDR image files of environment maps: OpenEXR (read) and Radiance RGBE ``.hdr``
(read and write, run-length encoded)."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from isolume.volumes.errors import IsolumeError
from isolume.volumes.writing import atomic_write


class EnvSpecError(IsolumeError):
    """A bad environment spec or file; the one-line message names it and what was expected."""


# ----------------------------------------------------------------------------- file reading
def read_exr(path: str | Path) -> tuple[np.ndarray, str | None]:
    """Read an OpenEXR image: (pixels (H, W, 3) float32, envmap kind "latlong"/"cube"/None).

    First part only; channels R, G, B (half or float), or Y (grey); alpha is ignored.
    """
    import OpenEXR  # lazy: only needed for .exr probes

    try:
        with OpenEXR.File(str(path), separate_channels=True) as f:
            header = f.header()
            channels = {name: ch.pixels for name, ch in f.channels().items()}
    except Exception as exc:  # the bindings raise plain RuntimeError/Exception on bad files
        raise EnvSpecError(f"{path}: cannot read as OpenEXR ({exc})") from exc
    envmap = header.get("envmap")
    kind = None
    if envmap is not None:
        kind = "cube" if "CUBE" in str(envmap).upper() else "latlong"
    if all(c in channels for c in "RGB"):
        planes = [channels[c] for c in "RGB"]
    elif "Y" in channels:
        planes = [channels["Y"]] * 3
    else:
        raise EnvSpecError(f"{path}: expected channels R, G, B (or Y), found {sorted(channels)}")
    shapes = {p.shape for p in planes}
    if len(shapes) != 1 or len(next(iter(shapes))) != 2:
        raise EnvSpecError(f"{path}: channels have different or subsampled shapes {shapes}")
    return np.stack([np.asarray(p, dtype=np.float32) for p in planes], axis=-1), kind


_HDR_RES = re.compile(rb"^([-+])Y\s+(\d+)\s+\+X\s+(\d+)$")


def read_hdr(path: str | Path) -> np.ndarray:
    """Read a Radiance RGBE (.hdr) image: (H, W, 3) float32 linear RGB.

    Supports flat and new-style run-length scanlines, resolution strings ``-Y H +X W``
    (standard, top row first) and ``+Y H +X W`` (bottom row first). Pixel values are
    divided by the product of the header's EXPOSURE values, as the format specifies.
    XYZE files and old-style RLE are refused.
    """
    data = Path(path).read_bytes()
    if not data.startswith(b"#?"):
        raise EnvSpecError(f"{path}: not a Radiance HDR file (no '#?' magic)")
    pos, exposure = 0, 1.0
    while True:
        end = data.find(b"\n", pos)
        if end < 0:
            raise EnvSpecError(f"{path}: truncated Radiance header")
        line = data[pos:end].strip()
        pos = end + 1
        if not line:
            break
        if line.startswith(b"FORMAT=") and line != b"FORMAT=32-bit_rle_rgbe":
            raise EnvSpecError(
                f"{path}: unsupported {line.decode(errors='replace')}, "
                "expected FORMAT=32-bit_rle_rgbe"
            )
        if line.startswith(b"EXPOSURE="):
            exposure *= _exposure(line, path)
    if not (math.isfinite(exposure) and exposure > 0):
        raise EnvSpecError(f"{path}: the product of the EXPOSURE values is {exposure:g}, "
                           "expected a positive finite number")
    end = data.find(b"\n", pos)
    match = _HDR_RES.match(data[pos:end].strip()) if end >= 0 else None
    if match is None:
        raise EnvSpecError(f"{path}: unsupported resolution line, expected '-Y H +X W'")
    h, w = int(match.group(2)), int(match.group(3))
    if h < 1 or w < 1:
        raise EnvSpecError(f"{path}: resolution {match.group(0).decode()!r}, expected a "
                           "height and a width of at least 1 pixel")
    rgbe = _decode_rgbe(data, end + 1, h, w, path)
    if match.group(1) == b"+":
        rgbe = rgbe[::-1]
    return _rgbe_to_float(rgbe) / np.float32(exposure)


def _exposure(line: bytes, path: str | Path) -> float:
    """The value of a header line ``EXPOSURE=V``: a positive finite number (pixel values
    are divided by it)."""
    text = line[9:].decode(errors="replace").strip()
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise EnvSpecError(f"{path}: EXPOSURE={text}, expected a positive finite number")
    return value


def _decode_rgbe(data: bytes, pos: int, h: int, w: int, path) -> np.ndarray:
    """RGBE bytes (H, W, 4) uint8 from flat or new-style RLE scanlines starting at pos."""
    lines = []
    try:
        for _ in range(h):
            if 8 <= w < 32768 and data[pos] == 2 and data[pos + 1] == 2 and data[pos + 2] < 128:
                if (data[pos + 2] << 8) | data[pos + 3] != w:
                    raise EnvSpecError(f"{path}: RLE scanline width does not match {w}")
                pos += 4
                comps = []
                for _c in range(4):
                    pieces, n = [], 0
                    while n < w:
                        count = data[pos]
                        if count > 128:
                            pieces.append(data[pos + 1 : pos + 2] * (count - 128))
                            pos += 2
                            n += count - 128
                        elif count > 0:
                            pieces.append(data[pos + 1 : pos + 1 + count])
                            pos += 1 + count
                            n += count
                        else:
                            raise EnvSpecError(f"{path}: bad RLE run of length 0")
                    comp = b"".join(pieces)
                    if pos > len(data):
                        raise IndexError("read past the end")
                    if len(comp) != w:
                        raise EnvSpecError(f"{path}: RLE run overruns the scanline")
                    comps.append(np.frombuffer(comp, dtype=np.uint8))
                lines.append(np.stack(comps, axis=1))
            else:
                flat = np.frombuffer(data, dtype=np.uint8, count=4 * w, offset=pos).reshape(w, 4)
                if np.any(np.all(flat[:, :3] == 1, axis=1)):
                    raise EnvSpecError(f"{path}: old-style RLE scanlines are not supported")
                lines.append(flat)
                pos += 4 * w
    except EnvSpecError:
        raise
    except (IndexError, ValueError) as exc:
        raise EnvSpecError(f"{path}: truncated pixel data ({h}x{w} expected)") from exc
    return np.stack(lines, axis=0)


def _rgbe_to_float(rgbe: np.ndarray) -> np.ndarray:
    """(..., 4) uint8 RGBE → (..., 3) float32: (m + 0.5) · 2^(e − 136), 0 where e = 0."""
    e = rgbe[..., 3].astype(np.int32)
    f = np.where(e > 0, np.ldexp(1.0, e - 136), 0.0)
    return ((rgbe[..., :3].astype(np.float64) + 0.5) * f[..., None]).astype(np.float32)


def write_hdr(path: str | Path, rgb: np.ndarray, rle: bool = True) -> None:
    """Write (H, W, 3) finite, non-negative linear RGB as Radiance RGBE (.hdr).

    rle: new-style run-length scanlines (needs 8 ≤ W < 32768), else flat.
    """
    rgb = np.asarray(rgb, dtype=np.float64)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"write_hdr expects (H, W, 3), got {rgb.shape}")
    if not np.all(np.isfinite(rgb)) or np.any(rgb < 0):
        raise ValueError("write_hdr needs finite, non-negative values")
    h, w = rgb.shape[:2]
    peak = rgb.max(axis=2)
    mant, expo = np.frexp(peak)
    visible = peak > 1e-38
    scale = np.where(visible, mant * 256.0 / np.where(visible, peak, 1.0), 0.0)
    rgbe = np.zeros((h, w, 4), dtype=np.uint8)
    rgbe[..., :3] = np.clip(np.floor(rgb * scale[..., None]), 0, 255).astype(np.uint8)
    rgbe[..., 3] = np.where(visible, expo + 128, 0).astype(np.uint8)
    out = [b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n", f"-Y {h} +X {w}\n".encode()]
    use_rle = rle and 8 <= w < 32768
    for y in range(h):
        if use_rle:
            out.append(bytes([2, 2, w >> 8, w & 255]))
            out.extend(_rle_encode(rgbe[y, :, c].tobytes()) for c in range(4))
        else:
            out.append(rgbe[y].tobytes())
    atomic_write(path, lambda tmp: Path(tmp).write_bytes(b"".join(out)), "light probe")


def _rle_encode(values: bytes) -> bytes:
    """New-style Radiance RLE of one component: runs of ≥ 4 equal bytes, else literals."""
    out, i, n = bytearray(), 0, len(values)
    while i < n:
        run = 1
        while i + run < n and run < 127 and values[i + run] == values[i]:
            run += 1
        if run >= 4:
            out += bytes([128 + run, values[i]])
            i += run
            continue
        j = i  # literal block until the next run of ≥ 4 (or 128 bytes)
        while j < n and j - i < 128:
            if j + 3 < n and values[j] == values[j + 1] == values[j + 2] == values[j + 3]:
                break
            j += 1
        out += bytes([j - i]) + values[i:j]
        i = j
    return bytes(out)


def read_image(path: str | Path) -> tuple[np.ndarray, str | None]:
    """(pixels (H, W, 3) float32, envmap hint or None) of a .exr or .hdr file."""
    p = Path(path)
    if not p.is_file():
        raise EnvSpecError(f"{path}: no such file (expected an .exr or .hdr probe)")
    ext = p.suffix.lower()
    if ext == ".exr":
        return read_exr(p)
    if ext in (".hdr", ".rgbe", ".pic"):
        return read_hdr(p), None
    raise EnvSpecError(
        f"{path}: unsupported image format {ext or '(none)'!r}, expected .exr or .hdr"
    )
