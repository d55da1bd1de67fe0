"""Images as numbers: the tone map every picture of difffog uses, and image error metrics.

NumPy only (the command line writes PNGs without importing matplotlib; ``difffog.plot``
re-exports these).
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from ._errors import DifffogError

GAMMA = 2.2
PERCENTILE = 99.5


def _arrays(images) -> list[np.ndarray]:
    if isinstance(images, Mapping):
        vals = list(images.values())
    elif isinstance(images, (list, tuple)):
        vals = list(images)
    else:
        vals = [images]
    out = [np.asarray(v, dtype=np.float64) for v in vals]
    if not out:
        raise DifffogError("no images given; pass an array or a dict of arrays")
    return out


def exposure(images, percentile: float = PERCENTILE) -> float:
    """The shared tone-map scale of one image or of all images of a dict/list together: the
    ``percentile`` of their finite pixels (1.0 if that is not positive)."""
    if not 0 < percentile <= 100:
        raise DifffogError(f"percentile must be in (0, 100], got {percentile}")
    pix = np.concatenate([a.ravel() for a in _arrays(images)])
    pix = pix[np.isfinite(pix)]
    scale = float(np.percentile(pix, percentile)) if pix.size else 0.0
    return scale if scale > 0 else 1.0


def tonemap(images, *, scale: float | None = None, percentile: float = PERCENTILE,
            gamma: float = GAMMA, dtype: str = "uint8"):
    """Tone-map linear radiance for viewing, with one exposure shared by all images.

    images: an (H, W) array, or a dict / list of them.
    scale: the radiance that maps to white (default: :func:`exposure`, the ``percentile`` of
        all pixels together).
    Returns ``(out, scale)``; ``out`` has the structure of ``images``: ``uint8`` in [0, 255]
    (``dtype="uint8"``) or float in [0, 1] (``dtype="float"``),
    ``clip(x / scale, 0, 1) ** (1 / gamma)``; non-finite pixels map to 0.
    """
    if dtype not in ("uint8", "float"):
        raise DifffogError(f"tonemap: dtype must be 'uint8' or 'float', got {dtype!r}")
    if scale is None:
        scale = exposure(images, percentile)
    elif not (scale > 0 and math.isfinite(scale)):
        raise DifffogError(f"tonemap: scale must be a positive number, got {scale}")
    scale = float(scale)

    def one(a):
        a = np.asarray(a, dtype=np.float64)
        x = np.clip(np.nan_to_num(a / scale, nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0)
        x = x ** (1.0 / gamma)
        return (x * 255 + 0.5).astype(np.uint8) if dtype == "uint8" else x

    if isinstance(images, Mapping):
        return {k: one(v) for k, v in images.items()}, scale
    if isinstance(images, (list, tuple)):
        return [one(v) for v in images], scale
    return one(images), scale


def image_errors(image, reference, noise: float | None = None) -> dict[str, float]:
    """Scalar errors of ``image`` against ``reference`` (both (H, W) radiance), as
    ``benchmarks/validate_references.py`` reports them: ``bias`` = mean(image)/mean(ref) − 1,
    ``rel_rmse`` = RMSE / mean(ref), and with ``noise`` (the reference's own per-pixel RMSE
    noise, in radiance) ``rel_rmse_corr`` = sqrt(max(RMSE² − noise², 0)) / mean(ref)."""
    img = np.asarray(image, dtype=np.float64)
    ref = np.asarray(reference, dtype=np.float64)
    if img.shape != ref.shape:
        raise DifffogError(f"image {img.shape} and reference {ref.shape} differ in "
                           "shape; render at the reference's resolution")
    mean_ref = float(ref.mean())
    if not mean_ref > 0:
        raise DifffogError("the reference's mean radiance is not positive; "
                           "relative errors are undefined")
    rmse = float(np.sqrt(np.mean((img - ref) ** 2)))
    out = {"bias": float(img.mean()) / mean_ref - 1.0, "rel_rmse": rmse / mean_ref}
    if noise is not None:
        out["rel_rmse_corr"] = math.sqrt(max(rmse**2 - float(noise) ** 2, 0.0)) / mean_ref
        out["ref_noise_rel"] = float(noise) / mean_ref
    return out
