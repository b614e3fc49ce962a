"""Reading an X-ray PNG, TIFF or JPEG (8 or 16 bit, grey or RGB with equal channels, one or more frames) with
Pillow: no geometry and no polarity in the file (bone dark assumed until the registration finds it).
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from carmreg.logic.errors import InputFileError, describe
from carmreg.logic.io.xray_image import (
    XrayParts,
    check_frame_size,
    grey_from_channels,
    select_frame,
)


def read_raster(path: Path, frame: int | None) -> XrayParts:
    """8/16-bit (or float) grey PNG/TIFF/JPEG via Pillow; multi-page TIFF needs ``frame``."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as image:
            n = int(getattr(image, "n_frames", 1))
            _, frame = select_frame(np.empty((n, 0)), frame, path)
            image.seek(frame)
            check_frame_size(*image.size, path)
            mode = image.mode
            pixels = _pil_to_array(image)
    except Image.DecompressionBombError:
        limit = 2 * Image.MAX_IMAGE_PIXELS // 10**6  # Pillow refuses above twice its warning threshold
        raise InputFileError(f"{path}: the image claims more than {limit} million pixels, far more than an "
                             "X-ray detector; the file is damaged or not an X-ray") from None
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError, TypeError, KeyError, IndexError,
            struct.error, EOFError, ZeroDivisionError, OverflowError, MemoryError) as exc:
        raise InputFileError(f"{path}: not a readable image ({describe(exc, 100)}); "
                             "the file may be truncated or of another format") from None
    meta = {"format": path.suffix.lower().lstrip("."), "mode": mode, "frame": frame, "n_frames": n}
    if pixels.ndim == 3:
        pixels = grey_from_channels(pixels, path, meta)
    part = XrayParts(pixels.astype(np.float32), True, meta=meta)
    part.sources["bone_dark"] = ("no polarity in PNG/TIFF/JPEG files: bone dark assumed until the registration "
                                 "finds it from the image")
    return part



def _pil_to_array(image) -> np.ndarray:
    """Pillow image -> numpy; palette and 1-bit images expanded; alpha dropped."""
    if image.mode == "P":
        image = image.convert("RGB")
    elif image.mode == "1":
        image = image.convert("L")
    elif image.mode in ("LA", "PA"):
        image = image.convert("RGBA" if image.mode == "PA" else "LA")
        return np.asarray(image)[..., 0]
    pixels = np.asarray(image)
    if pixels.ndim == 3 and pixels.shape[-1] == 4:
        pixels = pixels[..., :3]
    return pixels
