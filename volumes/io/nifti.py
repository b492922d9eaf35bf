"""NIfTI-1/2 volumes (``.nii``, ``.nii.gz``) via nibabel (extra ``nifti``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from isolume.volumes.core import VolumeError
from isolume.volumes.io.common import (
    RAS_TO_LPS,
    READ_ERRORS,
    Loaded,
    one_line,
    optional_module,
)


def load_nifti(path: Path) -> Loaded:
    """NIfTI via nibabel: [i, j, k] = [x, y, z] array -> (Z, Y, X).

    Spacing is the header zooms; the affine (nibabel's choice of sform and qform) maps
    voxels to RAS millimetres: its translation is the origin and its columns the axes'
    directions, both turned into LPS.
    """
    nib = optional_module("nibabel", path)
    try:
        img = nib.load(str(path))
        arr = np.asanyarray(img.dataobj)
        zooms = tuple(float(z) for z in img.header.get_zooms()[:3])
        affine = np.asarray(img.affine, np.float64)
    except (nib.filebasedimages.ImageFileError, *READ_ERRORS) as exc:
        raise VolumeError(f"{path}: not a readable NIfTI file: {one_line(exc)}") from None
    while arr.ndim > 3 and arr.shape[-1] == 1:
        arr = arr[..., 0]
    if arr.ndim != 3:
        raise VolumeError(
            f"{path}: expected a 3-D scalar NIfTI image (x, y, z), got shape {arr.shape}"
        )
    return arr.transpose(2, 1, 0), zooms, affine[:3, 3], (affine[:3, :3], RAS_TO_LPS)
