"""A folder of photos as a capture: the images a phone user has instead of a video.

The photos are the capture's frames, numbered in the order of their file names (any order
is accepted: the pose stage matches every pair and puts the registered views in sweep order
itself). Each photo is turned upright by its EXIF orientation. All photos must have one size
once upright (one camera, one focal length: the pose stage calibrates a single camera); the
EXIF focal length, when the photos carry one, is the pose stage's initial focal length.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from facecap_core.errors import InputError

PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png", ".heic", ".heif")
"""File types read as photos (case-insensitive); HEIC/HEIF through ``pillow-heif``."""
MIN_PHOTOS = 5
"""Fewer photos cannot give a multi-view reconstruction of a face."""
MAX_PHOTOS = 1000
"""More photos than this are refused: a face needs tens, and matching grows with the count."""


@dataclass(frozen=True)
class PhotoInfo:
    """What a photo folder holds (sizes upright)."""

    paths: tuple[Path, ...]
    width: int
    height: int
    focal_px: float | None  # from EXIF, at this width; None when the photos do not say


def _register_heif() -> None:
    try:
        from pillow_heif import register_heif_opener
    except ImportError:  # HEIC photos then fail to open with a message naming the package
        return
    register_heif_opener()


def list_photos(folder: str | Path) -> list[Path]:
    """The photo files of ``folder`` (not its subfolders), sorted by name."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"photo folder not found: {folder}")
    return sorted((p for p in folder.iterdir()
                   if p.is_file() and p.suffix.lower() in PHOTO_SUFFIXES
                   and not p.name.startswith(".")), key=lambda p: p.name)


def _open(path: Path, decode: bool = True):
    """The photo upright (``decode``), or opened lazily: its header and EXIF only."""
    from PIL import Image, ImageOps, UnidentifiedImageError

    _register_heif()
    try:
        image = Image.open(path)
        if not decode:
            return image
        image.load()
    except UnidentifiedImageError:
        hint = " (HEIC needs the pillow-heif package)" if path.suffix.lower() in (
            ".heic", ".heif") else ""
        raise InputError(f"{path} is not a readable image{hint}; give JPEG or PNG photos") \
            from None
    except (OSError, ValueError, SyntaxError) as exc:
        raise InputError(f"{path} cannot be decoded ({type(exc).__name__}); the file is "
                         "damaged or truncated") from None
    return ImageOps.exif_transpose(image)


def _upright_size(image) -> tuple[int, int]:
    """Width and height once turned by the EXIF orientation (5-8 swap the axes)."""
    w, h = image.size
    return (h, w) if image.getexif().get(0x0112) in (5, 6, 7, 8) else (w, h)


def _exif_focal_px(image, width: int, height: int) -> float | None:
    """Focal length in pixels of the upright image, from EXIF (35 mm equivalent preferred:
    it needs no sensor size), or None."""
    exif = image.getexif()
    sub = exif.get_ifd(0x8769) if exif else {}
    f35 = sub.get(0xA405) or exif.get(0xA405)  # FocalLengthIn35mmFilm
    if f35:
        # The 35 mm equivalent is defined on the 36 x 24 mm frame's diagonal.
        return float(f35) / np.hypot(36.0, 24.0) * np.hypot(width, height)
    f_mm = sub.get(0x920A)  # FocalLength
    x_res, unit = sub.get(0xA20E), sub.get(0xA210)  # FocalPlaneXResolution, its unit
    if f_mm and x_res and unit in (2, 3):
        px_per_mm = float(x_res) / (25.4 if unit == 2 else 10.0)
        focal = float(f_mm) * px_per_mm
        # The resolution is of the sensor's long side; the stored image may be downscaled.
        native_long = sub.get(0xA002) or max(width, height)
        return focal * max(width, height) / float(native_long)
    return None


def read_photo(path: str | Path, grey: bool = False) -> np.ndarray:
    """One photo upright, as RGB uint8 (H, W, 3) or grey (H, W)."""
    image = _open(Path(path))
    return np.asarray(image.convert("L" if grey else "RGB"))


def probe_photos(folder: str | Path) -> PhotoInfo:
    """Sizes and focal length of a photo folder; refuses too few photos or mixed sizes."""
    folder = Path(folder)
    paths = list_photos(folder)
    if len(paths) < MIN_PHOTOS:
        raise InputError(f"{folder} holds {len(paths)} photo(s) ({', '.join(PHOTO_SUFFIXES)});"
                         f" a capture needs at least {MIN_PHOTOS} photos of the face from the "
                         "front and both sides")
    if len(paths) > MAX_PHOTOS:
        raise InputError(f"{folder} holds {len(paths)} photos, more than {MAX_PHOTOS}; give a "
                         "folder of one capture (tens of photos are plenty)")
    sizes: dict[tuple[int, int], list[str]] = {}
    focals = []
    for path in paths:
        # The header is enough: a photo that fails to decode is named when it is read.
        with _open(path, decode=False) as image:
            size = _upright_size(image)
            sizes.setdefault(size, []).append(path.name)
            focals.append(_exif_focal_px(image, *size))
    if len(sizes) > 1:
        listed = "; ".join(f"{w}x{h}: {len(n)} ({', '.join(n[:2])}{', ...' if len(n) > 2 else ''})"
                           for (w, h), n in sorted(sizes.items(), key=lambda s: -len(s[1])))
        raise InputError(f"{folder} mixes photo sizes ({listed}); give photos from one camera "
                         "at one size (no crops, no screenshots, one orientation)")
    (width, height), = sizes
    known = [f for f in focals if f]
    focal = float(np.median(known)) if known else None
    return PhotoInfo(tuple(paths), width, height, focal)
