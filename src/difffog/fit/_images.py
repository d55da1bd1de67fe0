"""Targets and masks from files: photographs and renders as PNG (8- and 16-bit), TIFF (8/16-bit
integer, float), OpenEXR (half, float) and JPEG, read by OpenImageIO, and ``.npy`` arrays.

A fit compares linear radiance.  8-bit files are sRGB-encoded by convention and are decoded by
the exact IEC 61966-2-1 inverse; 16-bit and float files are taken as linear (``transfer``
overrides either way).  Integer code values are scaled to [0, 1]; the unknown scale of a
photograph is the fit's ``exposure`` unknown.  Colour is reduced to the renderer's one channel
*after* linearisation: the Rec. 709 / sRGB luminance Y = 0.2126 R + 0.7152 G + 0.0722 B, or
one channel.  An alpha channel is not radiance: a target drops it, a mask uses it
(:func:`load_mask`), so a photograph exported with its unusable parts transparent masks
itself."""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from .._errors import DifffogError

#: file suffix → format name; OpenImageIO reads all but .npy
FORMATS = {".npy": "NumPy", ".png": "PNG", ".tif": "TIFF", ".tiff": "TIFF", ".exr": "OpenEXR",
           ".jpg": "JPEG", ".jpeg": "JPEG"}
CHANNELS = ("luminance", "r", "g", "b")
TRANSFERS = ("auto", "srgb", "linear")
#: Rec. 709 / sRGB primaries' luminance weights (IEC 61966-2-1), of linear R, G, B
LUMINANCE = (0.2126, 0.7152, 0.0722)
_SUPPORTED = ".npy (linear radiance), .png (8/16-bit), .tif/.tiff (8/16-bit, float), .exr " \
             "(half, float), .jpg/.jpeg (8-bit)"


def srgb_to_linear(v):
    """The exact inverse of the sRGB transfer function (IEC 61966-2-1): encoded values in
    [0, 1] to linear ones, V / 12.92 up to 0.04045, ((V + 0.055) / 1.055)^2.4 above."""
    v = np.asarray(v, np.float64)
    return np.where(v <= 0.04045, v / 12.92, ((np.maximum(v, 0.04045) + 0.055) / 1.055) ** 2.4)


def bad_pixels(bad: np.ndarray) -> str:
    """'N pixel(s), the first at row R, column C': the True pixels of a (H, W) boolean image,
    the first in row-major order."""
    n = int(bad.sum())
    r, c = np.unravel_index(int(np.argmax(bad)), bad.shape)
    return f"{n} pixel{'s' if n != 1 else ''}, the first at row {r}, column {c}"


def _read(path: Path, what: str):
    """(pixels (H, W, C) in the file's own type, channel names, alpha index or None, format
    name), or a one-line error."""
    suffix = path.suffix.lower()
    if suffix not in FORMATS:
        raise DifffogError(f"{what}: unknown image format '{path.suffix or path.name}'; "
                           f"supported: {_SUPPORTED}")
    if not path.is_file():
        raise DifffogError(f"{what}: no such file")
    if suffix == ".npy":
        try:
            a = np.load(path, allow_pickle=False)
        except Exception as e:  # noqa: BLE001 - any unreadable file gets the same answer
            raise DifffogError(f"{what}: cannot read it as .npy ({e})") from None
        if a.ndim == 2:
            a = a[..., None]
        if a.ndim != 3 or a.dtype.kind not in "biuf":
            raise DifffogError(f"{what}: expected an (H, W) or (H, W, channels) array of "
                               f"numbers, got shape {a.shape} of {a.dtype}")
        names = {1: ("Y",), 2: ("Y", "A"), 3: ("R", "G", "B"), 4: ("R", "G", "B", "A")}
        nc = a.shape[2]
        return a, names.get(nc, ("?",) * nc), (nc - 1 if nc in (2, 4) else None), "NumPy"
    import OpenImageIO as oiio

    config = oiio.ImageSpec()
    # the colour values as stored: OpenImageIO would otherwise premultiply them by alpha
    config.attribute("oiio:UnassociatedAlpha", 1)
    inp = oiio.ImageInput.open(str(path), config)
    if inp is None:
        raise DifffogError(f"{what}: cannot read it as {FORMATS[suffix]} "
                           f"({' '.join(oiio.geterror().split()) or 'unreadable'})")
    try:
        spec = inp.spec()
        orientation = spec.get_int_attribute("Orientation", 1)
        if orientation != 1:
            raise DifffogError(
                f"{what}: the file is stored rotated or mirrored (orientation tag "
                f"{orientation}); save it upright (e.g. 'apply the orientation' on export)")
        a = inp.read_image(format="unknown")  # the file's own pixel type
        if a is None:
            raise DifffogError(f"{what}: cannot read its pixels "
                               f"({' '.join(oiio.geterror().split())})")
        names = tuple(spec.channelnames)
        alpha = spec.alpha_channel if spec.alpha_channel >= 0 else None
        return np.asarray(a).reshape(spec.height, spec.width, spec.nchannels), names, alpha, \
            inp.format_name()
    finally:
        inp.close()


def _colour(a: np.ndarray, names, alpha, what: str) -> tuple[np.ndarray, tuple[str, ...]]:
    """The colour channels (H, W, 1 or 3) without alpha, as R, G, B where there are three."""
    keep = [i for i in range(a.shape[2]) if i != alpha]
    cn = tuple(names[i].upper() for i in keep)
    if len(keep) == 3 and set(cn) == {"R", "G", "B"}:
        keep = [keep[cn.index(k)] for k in "RGB"]
    elif len(keep) not in (1, 3):
        raise DifffogError(
            f"{what}: {a.shape[2]} channels ({', '.join(names)}); supported: 1 (grey) or 3 "
            f"(R, G, B), each with an optional alpha; save the image as grey or RGB")
    return a[..., keep], tuple(names[i] for i in keep)


def check_options(channel: str, transfer: str) -> None:
    """One-line errors for a channel or transfer that is not one of the choices."""
    if channel not in CHANNELS:
        raise DifffogError(f"channel {channel!r}: choose 'luminance' (Y = 0.2126 R + 0.7152 G + "
                           f"0.0722 B of the linear values), 'r', 'g' or 'b'")
    if transfer not in TRANSFERS:
        raise DifffogError(f"transfer {transfer!r}: choose 'auto' (sRGB for 8-bit files, linear "
                           f"for 16-bit and float), 'srgb' or 'linear'")


def _scale(a: np.ndarray, transfer: str, what: str) -> tuple[np.ndarray, str]:
    """(linear float64 values, the transfer applied) of an image file's pixels."""
    if a.dtype == np.uint8 or a.dtype == np.uint16:
        v = a.astype(np.float64) / np.iinfo(a.dtype).max
        if transfer == "auto":
            transfer = "srgb" if a.dtype == np.uint8 else "linear"
    elif a.dtype.kind == "f":
        v = a.astype(np.float64)
        transfer = "linear" if transfer == "auto" else transfer
    else:
        raise DifffogError(f"{what}: pixels of type {a.dtype}; supported: 8- or 16-bit "
                           f"unsigned integers, or float (half, single, double)")
    return (srgb_to_linear(v) if transfer == "srgb" else v), transfer


def _reduce(v: np.ndarray, names, channel: str, what: str) -> np.ndarray:
    """The (H, W) image of ``channel`` from linear grey (H, W, 1) or R, G, B (H, W, 3)."""
    if v.shape[2] == 1:
        if channel != "luminance":
            raise DifffogError(f"{what}: a grey image ({names[0]}) has no channel "
                               f"'{channel}'; use channel 'luminance'")
        return v[..., 0]
    if channel == "luminance":
        return v @ np.asarray(LUMINANCE)
    return v[..., "rgb".index(channel)]


def load_target(path: str | os.PathLike, *, channel: str = "luminance", transfer: str = "auto",
                mask=None, what: str | None = None) -> tuple[np.ndarray, dict]:
    """A target image from a file, as linear radiance.

    path: .npy (linear radiance as stored, (H, W) or (H, W, 1 | 3 | 4)), .png (8/16-bit),
        .tif/.tiff (8/16-bit, float), .exr (half, float) or .jpg/.jpeg; the first image of a
        multi-image file.
    channel: "luminance" (Y = 0.2126 R + 0.7152 G + 0.0722 B of the linear values, Rec. 709 /
        sRGB primaries) or "r", "g", "b"; a grey image is its own luminance.  Alpha is dropped.
    transfer: "auto" (sRGB for 8-bit files, linear for 16-bit and float ones), "srgb" (undo
        the exact IEC 61966-2-1 curve) or "linear".  Integers are scaled to [0, 1] first
        (code value / 255 or / 65535); float values are kept as stored.
    mask: (H, W) weights or booleans: pixels where it is zero are not checked (they are not
        fitted).
    what: how errors name the file (default: its path).

    Returns (float64 (H, W) linear radiance, info) where info (JSON-able) records the path,
    format, pixel type, transfer applied, channel, the file's channels and whether an alpha
    channel was dropped.  Raises a one-line :class:`difffog.DifffogError` for a missing or
    unreadable file, an unknown format, an unsupported channel count or pixel type, a rotated
    file, non-finite pixels or negative values in a float file (unmasked ones).
    """
    check_options(channel, transfer)
    path = Path(path)
    what = what or str(path)
    raw, names, alpha, fmt = _read(path, what)
    colour, cnames = _colour(raw, names, alpha, what)
    if fmt != "NumPy":
        v, applied = _scale(colour, transfer, what)
    elif transfer in ("auto", "linear"):
        v, applied = colour.astype(np.float64), "linear"
    else:
        raise DifffogError(f"{what}: a .npy target holds linear radiance as stored; transfer "
                           f"{transfer!r} applies to image files")
    img = _reduce(v, cnames, channel, what)
    check = np.ones(img.shape, bool)
    if mask is not None:
        m = np.asarray(mask)
        if m.shape != img.shape:
            raise DifffogError(f"{what}: its mask is {m.shape[::-1]} pixels (width, height), "
                               f"the image {img.shape[::-1]}; give a mask of the image's size")
        check = m != 0
    band = "image" if v.shape[2] == 1 else f"{channel} image"
    bad = check & ~np.isfinite(img)
    if bad.any():
        raise DifffogError(f"{what}: non-finite values (NaN or infinite) in its {band}: "
                           f"{bad_pixels(bad)}; replace them or mask them out (a zero weight)")
    neg = check & (img < 0)
    if fmt != "NumPy" and raw.dtype.kind == "f" and neg.any():
        raise DifffogError(f"{what}: negative values in its {band}: {bad_pixels(neg)} "
                           f"({img[neg][0]:.3g}); radiance is >= 0: clip them at 0 or mask them "
                           f"out (a zero weight)")
    info = {"path": str(path), "format": fmt, "dtype": str(raw.dtype), "transfer": applied,
            "channel": channel if v.shape[2] == 3 else "grey", "channels": list(names),
            "alpha": "dropped" if alpha is not None else None,
            "size": [img.shape[1], img.shape[0]]}
    return img, info


def load_mask(path: str | os.PathLike, *, what: str | None = None) -> np.ndarray:
    """Per-pixel weights (H, W) from a file: a .npy array of weights >= 0 as stored; an image
    file is a 0/1 mask, 1 where its alpha channel (if it has one), else any channel, is
    nonzero.  So the target's own file, with its unusable parts transparent, is its mask."""
    path = Path(path)
    what = what or str(path)
    raw, names, alpha, fmt = _read(path, what)
    if fmt == "NumPy":
        if raw.shape[2] != 1:
            raise DifffogError(f"{what}: a .npy mask holds (H, W) weights, got shape "
                               f"{raw.shape}")
        return raw[..., 0].astype(np.float64)
    used = raw[..., alpha] if alpha is not None else raw.max(axis=2)
    if not np.all(np.isfinite(used)):
        raise DifffogError(f"{what}: non-finite mask values: "
                           f"{bad_pixels(~np.isfinite(used))}; write 0 where a pixel is not "
                           f"to be used, nonzero where it is")
    return (used != 0).astype(np.float64)


def load_files(targets: Mapping[str, Any], weights: Mapping[str, Any] | None, *, channel: str,
               transfer: str):
    """A fit's targets and weights with file paths (str or PathLike) read into arrays, the
    others as they are: (targets, weights, {camera: target file info}, {camera: mask path}).
    Masks are read first, so that masked-out pixels of a target are not checked."""
    check_options(channel, transfer)
    is_path = lambda x: isinstance(x, (str, os.PathLike))  # noqa: E731
    weights = dict(weights or {})
    mask_files = {}
    for name, w in weights.items():
        if is_path(w):
            weights[name] = load_mask(w, what=f"mask '{name}' ({w})")
            mask_files[name] = str(w)
    out, target_files = {}, {}
    for name, img in targets.items():
        if is_path(img):
            out[name], target_files[name] = load_target(
                img, channel=channel, transfer=transfer, mask=weights.get(name),
                what=f"target '{name}' ({img})")
        else:
            out[name] = img
    return out, (weights or None), target_files, mask_files
