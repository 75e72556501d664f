"""Texture images: decoded and checked here, so that Panda3D only ever sees pixels.

Panda3D's own image readers end the interpreter (exit status 1, no exception) on a
truncated BMP, PPM or TGA file and accept a truncated JPEG. Pillow decodes every image
file instead: fully (a truncated file raises; LOAD_TRUNCATED_IMAGES is left off), and
any failure becomes a ValueError naming the argument and the file.
"""
from __future__ import annotations

import os

import numpy as np
import torch

from ..util.validation import describe, regular_file


def load_image(path, *, name: str = "texture") -> np.ndarray:
    """Decode an image file into uint8 pixels [h, w, 3] (or [h, w, 4] if it has alpha), row 0 on top."""
    path = regular_file(name, path, kind="image")
    try:
        return decode_image(path)
    except ValueError as reason:
        raise ValueError(f"{name}: image file {path!r} could not be decoded: {reason}") from reason.__cause__


def decode_image(path: str) -> np.ndarray:
    """load_image without the path checks; raises ValueError(the reason) for a file that
    is not a complete image."""
    from PIL import Image

    try:
        with Image.open(path) as image:
            image.load()  # decodes every pixel: a truncated file raises here
            has_alpha = "A" in image.getbands() or "transparency" in image.info
            pixels = np.asarray(image.convert("RGBA" if has_alpha else "RGB"))
    except Exception as error:  # Pillow's format plugins raise many types on corrupt data
        raise ValueError(f"{type(error).__name__}: {error}") from error
    return np.ascontiguousarray(pixels, dtype=np.uint8)


def texture_pixels(texture, *, name: str = "texture") -> np.ndarray:
    """A texture argument as checked uint8 pixels [h, w, 3|4] that the caller owns.

    texture: an image file path (str or os.PathLike), or a uint8 numpy array / CPU tensor
    [h, w, 3|4] with row 0 on top (copied, so later writes to it change nothing here)."""
    if isinstance(texture, (str, os.PathLike)):
        return load_image(texture, name=name)
    if isinstance(texture, torch.Tensor):
        if texture.device.type != "cpu" or texture.layout != torch.strided:
            raise ValueError(f"{name} must be a dense CPU tensor, got {describe(texture)}")
        texture = texture.detach().numpy()
    if not isinstance(texture, np.ndarray):
        raise TypeError(f"{name} must be an image file path or a uint8 array [h, w, 3|4], got {describe(texture)}")
    if texture.dtype != np.uint8 or texture.ndim != 3 or texture.shape[2] not in (3, 4) or min(texture.shape[:2]) < 1:
        raise ValueError(f"{name} must be a uint8 array [h, w, 3|4] with h, w >= 1, got {describe(texture)}")
    return np.array(texture, order="C", copy=True)
