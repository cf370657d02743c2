"""Label images of a fit of several materials (``--materials LABELS``): one integer per pixel, 0 .. M-1 the
material, not fitted < 0 in a ``.npy`` and 255 / 65535 in an 8- / 16-bit one-channel ``.png``; on the fit's pixel
grid or a raw mosaic's sensor grid (:func:`fmbrdf_mi.fit.evaluate.materials.check_labels`)."""
from __future__ import annotations

import os

import numpy as np

from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.inputs.observations import check_file, read_array

#: The value of a pixel that is not fitted, by the PNG's bit depth.
PNG_NOT_FITTED = {8: 255, 16: 65535}


def read_labels(path, what="--materials"):
    """The label image in ``path`` as int64 (H, W), -1 not fitted; else InputError naming ``what`` and the file."""
    path = check_file(os.fspath(path), what)
    ext, name = os.path.splitext(path)[1].lower(), f"{what} {path}"
    if ext == ".npy":
        a = read_array(path, what)
        if a.ndim != 2 or a.dtype.kind not in "iuf":
            raise InputError(f"{name}: expected a 2-D integer array of labels (0 .. M-1, < 0 not fitted), got "
                             f"{a.dtype} of shape {a.shape}")
        if a.dtype.kind == "f" and (not np.all(np.isfinite(a)) or np.any(a != np.round(a))):
            raise InputError(f"{name}: labels must be integers (0 .. M-1, < 0 not fitted)")
        return np.maximum(a.astype(np.int64), -1)
    if ext == ".png":
        from PIL import Image

        try:
            with Image.open(path) as im:
                mode = im.mode
                a = np.asarray(im)
        except Exception as exc:  # noqa: BLE001
            raise InputError(f"{name}: not a readable .png file ({exc})") from None
        if mode not in ("L", "P", "I;16", "I;16B", "I;16L", "I"):
            raise InputError(f"{name}: expected a one-channel PNG (grey, 16-bit grey or palette) of labels "
                             f"0 .. M-1, got mode {mode}")
        a = a.astype(np.int64)
        return np.where((a == PNG_NOT_FITTED[16 if mode.startswith("I") else 8]) | (a < 0), -1, a)
    raise InputError(f"{name}: unsupported file type '{ext}' (labels: .npy or a one-channel .png)")


def read_uv_labels(path, what="--materials"):
    """A shape's uv label image (``render --materials``, the dataset's ``shape.labels``): :func:`read_labels`
    with every texel a material, M <= 255 (the label PNGs written are 8-bit)."""
    labels = read_labels(path, what)
    if labels.min() < 0:
        raise InputError(f"{what} {os.fspath(path)}: every texel of the shape's uv needs a material (0 .. M-1); "
                         "found texels marked not fitted")
    if labels.max() >= 255:
        raise InputError(f"{what} {os.fspath(path)}: at most 255 materials (the label PNGs written are 8-bit)")
    return labels


def write_labels(path, labels):
    """``labels`` (H, W) (< 0 not fitted) as an 8-bit grey PNG (255 not fitted; M <= 255)."""
    from PIL import Image

    lab = np.asarray(labels, dtype=np.int64)
    if lab.max() >= 255:
        raise InputError(f"labels: {int(lab.max()) + 1} materials do not fit an 8-bit PNG (at most 255)")
    Image.fromarray(np.where(lab < 0, 255, lab).astype(np.uint8), mode="L").save(path)
