"""A folder of photos as a capture: the images a phone user has instead of a video.

The photos are the capture's frames, numbered in the order of their file names (any order
is accepted: the pose stage matches every pair and puts the registered views in sweep order
itself). Each photo is turned upright by its EXIF orientation. All photos must have one size
once upright (one camera, one focal length: the pose stage calibrates a single camera); the
EXIF focal length, when the photos carry one, is the pose stage's initial focal length.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image, ImageOps, UnidentifiedImageError

from facecap_core.errors import InputError
from facecap_core.settings import settings

# Imported where used: pillow-heif is optional: without it HEIC photos are refused with a message.

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


def _register_heif() -> bool:
    """Whether HEIC/HEIF photos can be read (``pillow-heif`` registered with Pillow)."""
    try:
        from pillow_heif import register_heif_opener
    except ImportError:  # HEIC photos then fail to open with a message naming the package
        return False
    register_heif_opener()
    return True


def _pillow():
    """Pillow's ``Image`` module, set up to read photos; and the formats a photo may have.

    facecap checks a photo's size itself, from its header and before decoding it
    (:func:`_check_size`), and says in one line what is wrong with a photo. Pillow's own
    size check would come first, inside ``Image.open``: a warning line above 89 megapixels,
    an exception above 179 that names no file. Both are off, for the process: Pillow reads
    no other image in facecap. Its other warnings (a malformed EXIF block or MPO index) are
    about photos that are read anyway, and would be extra lines on the console."""

    Image.MAX_IMAGE_PIXELS = None
    # Added on every call (a duplicate filter is replaced, not added): a test harness or a
    # caller's catch_warnings() may have put the filters back since the last call.
    warnings.filterwarnings("ignore", module=r"PIL\.")
    # Only the photo formats: the size check reads the header's size, which other formats
    # (TIFF tiles, GIF and ICO frames) do not bound.
    return Image, ("JPEG", "PNG", "HEIF") if _register_heif() else ("JPEG", "PNG")


def list_photos(folder: str | Path) -> list[Path]:
    """The photo files of ``folder`` (not its subfolders), sorted by name."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"photo folder not found: {folder}")
    return sorted((p for p in folder.iterdir()
                   if p.is_file() and p.suffix.lower() in PHOTO_SUFFIXES
                   and not p.name.startswith(".")), key=lambda p: p.name)


def _open(path: Path, decode: bool = True):
    """The photo upright (``decode``), or opened lazily: its header and EXIF only. A photo
    larger than ``FACECAP_MAX_SIDE_PX`` is refused before its pixels are read."""

    Image, formats = _pillow()
    try:
        image = Image.open(path, formats=formats)
    except UnidentifiedImageError:
        hint = " (HEIC needs the pillow-heif package)" if path.suffix.lower() in (
            ".heic", ".heif") else ""
        raise InputError(f"{path} is not a readable image{hint}; give JPEG or PNG photos") \
            from None
    except (OSError, ValueError, SyntaxError) as exc:
        raise _damaged(path, exc) from None
    _check_size(image, path)
    if not decode:
        return image
    try:
        image.load()
    except (OSError, ValueError, SyntaxError) as exc:
        raise _damaged(path, exc) from None
    return ImageOps.exif_transpose(image)


def _damaged(path: Path, exc: Exception) -> InputError:
    return InputError(f"{path} cannot be decoded ({type(exc).__name__}); the file is damaged "
                      "or truncated")


def _check_size(image, path: Path) -> None:
    """Refuse (and close) a photo whose header's size is over the longest side a run
    accepts, as a video of that size is: decoding it could take more memory than there is."""

    limit, (w, h) = settings().max_side_px, image.size
    if max(w, h) > limit:
        image.close()
        raise InputError(f"{path} is {w}x{h} pixels, larger than the limit of {limit} on the "
                         f"long side; give photos of {limit} pixels or less on the long side "
                         "(a phone's 12-megapixel photos are plenty)")


def _upright_size(image) -> tuple[int, int]:
    """Width and height once turned by the EXIF orientation (5-8 swap the axes)."""
    w, h = image.size
    return (h, w) if image.getexif().get(0x0112) in (5, 6, 7, 8) else (w, h)


def _positive(value) -> float | None:
    """An EXIF number as a float, or None where it is absent, not a number, not finite or
    not positive (a rational of denominator 0 reads as NaN): such a tag says nothing."""
    try:
        number = float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return number if math.isfinite(number) and number > 0 else None


def _exif_focal_px(image, width: int, height: int) -> float | None:
    """Focal length in pixels of the upright image, from EXIF (35 mm equivalent preferred:
    it needs no sensor size), or None. A tag that is not a positive number is ignored, as
    if the photo did not carry it."""
    exif = image.getexif()
    sub = exif.get_ifd(0x8769) if exif else {}
    f35 = _positive(sub.get(0xA405)) or _positive(exif.get(0xA405))  # FocalLengthIn35mmFilm
    if f35:
        # The 35 mm equivalent is defined on the 36 x 24 mm frame's diagonal.
        return _positive(f35 / np.hypot(36.0, 24.0) * np.hypot(width, height))
    f_mm = _positive(sub.get(0x920A))  # FocalLength
    # FocalPlaneXResolution and its unit (2: inch, 3: cm).
    x_res, unit = _positive(sub.get(0xA20E)), sub.get(0xA210)
    if f_mm and x_res and unit in (2, 3):
        px_per_mm = x_res / (25.4 if unit == 2 else 10.0)
        # The resolution is of the sensor's long side; the stored image may be downscaled.
        native_long = _positive(sub.get(0xA002)) or max(width, height)
        return _positive(f_mm * px_per_mm * max(width, height) / native_long)
    return None


def _size_and_focal(path: Path) -> tuple[tuple[int, int], float | None]:
    """A photo's upright size and EXIF focal length (pixels, or None), from its header: a
    photo whose pixels do not decode is named when it is read. A PNG's EXIF may follow its
    pixels, though, and Pillow decodes them to reach it."""
    with _open(path, decode=False) as image:
        try:
            size = _upright_size(image)
            return size, _exif_focal_px(image, *size)
        except (OSError, ValueError, SyntaxError) as exc:
            raise _damaged(path, exc) from None


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
        size, focal = _size_and_focal(path)
        sizes.setdefault(size, []).append(path.name)
        focals.append(focal)
    if len(sizes) > 1:
        listed = "; ".join(f"{w}x{h}: {len(n)} ({', '.join(n[:2])}{', ...' if len(n) > 2 else ''})"
                           for (w, h), n in sorted(sizes.items(), key=lambda s: -len(s[1])))
        raise InputError(f"{folder} mixes photo sizes ({listed}); give photos from one camera "
                         "at one size (no crops, no screenshots, one orientation)")
    (width, height), = sizes
    known = [f for f in focals if f]
    focal = float(np.median(known)) if known else None
    return PhotoInfo(tuple(paths), width, height, focal)
