"""Targets of a fit: images (one or several views, arrays or files read by ``_images.py``)
checked against the forward model's cameras, reduced to its resolution by box-averaging, with
per-pixel weights."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import numpy as np

from .._errors import DifffogError
from ..scene._description import Scene
from ._images import bad_pixels


def reduced_scene(scene: Scene, names: list[str], downsample: int) -> Scene:
    cams = []
    for c in scene.cameras:
        if c.name not in names:
            continue
        if c.width % downsample or c.height % downsample:
            raise DifffogError(
                f"downsample {downsample}: camera '{c.name}' is {c.width}x{c.height}, not "
                f"divisible by {downsample}; choose a common divisor of its width and height")
        cams.append(dataclasses.replace(c, resolution=(c.width // downsample,
                                                       c.height // downsample)))
    return scene.replace(cameras=tuple(cams))


def _block_mean(img: np.ndarray, k: int) -> np.ndarray:
    H, W = img.shape
    return img.reshape(H // k, k, W // k, k).mean(axis=(1, 3))


def _size_error(name: str, info: dict, shape, full, want, downsample: int) -> DifffogError:
    """A target file of the wrong size: both sizes (width x height) and the two fixes."""
    rendered = (f", rendered at {want[1]}x{want[0]} with downsample {downsample}"
                if want != (full.height, full.width) else "")
    return DifffogError(
        f"target '{name}' ({info['path']}): the image is {shape[1]}x{shape[0]} pixels (width x "
        f"height) but camera '{name}' is {full.width}x{full.height}{rendered}; resize (or crop) "
        f"the image to {full.width}x{full.height}, or set the camera's resolution to the "
        f"image's and render it at 1/K of that size with downsample K")


def prepare_targets(scene: Scene, fwd, targets: Mapping[str, Any], weights, downsample: int,
                    files: Mapping[str, dict] | None = None):
    """Check and downsample targets (and weights) to the forward model's camera shapes.
    ``files``: {camera: info} of the targets read from files (their errors name the file)."""
    files = files or {}
    if not isinstance(targets, Mapping) or not targets:
        raise DifffogError("targets: give a dict {camera name: (H, W) image}, at least one")
    out_t, out_w = {}, {}
    fcams = {c.name: c for c in fwd.cameras}
    weights = {} if weights is None else weights
    for name in weights:
        if name not in targets:
            raise DifffogError(f"weights: camera '{name}' has no target; weights must be keyed "
                               f"like the targets ({', '.join(targets)})")
    for name, img in targets.items():
        scene.camera(name)  # clear error for an unknown camera
        if name not in fcams:
            raise DifffogError(f"target '{name}': the forward model has no camera '{name}' "
                               f"(it has {', '.join(fcams)})")
        cam = fcams[name]
        full = scene.camera(name)
        a = np.asarray(img, np.float64)
        w = weights.get(name)
        w = np.ones_like(a) if w is None else np.asarray(w, np.float64)
        if w.dtype == bool:
            w = w.astype(np.float64)
        if w.shape != a.shape:
            raise DifffogError(f"weights '{name}': shape {w.shape} differs from its target's "
                               f"{a.shape}")
        bad = (w > 0) & ~np.isfinite(a)
        if bad.any():
            raise DifffogError(f"target '{name}': NaN or infinite values: {bad_pixels(bad)}; "
                               f"mask them with a zero weight or replace them")
        want = (cam.height, cam.width)
        if a.shape == want:
            pass
        elif a.shape == (full.height, full.width) and (full.height, full.width) != want:
            k = full.height // cam.height
            if (full.height, full.width) != (cam.height * k, cam.width * k):
                raise DifffogError(f"target '{name}': shape {a.shape} cannot be reduced to the "
                                   f"forward model's {want}")
            # the reduced camera's pixel is the box-filtered footprint of k×k full pixels:
            # the weighted mean of the target over it, with the total weight (masked-out
            # pixels, NaN or not, count as 0)
            wa = _block_mean(w * np.where(w > 0, a, 0.0), k)
            ws = _block_mean(w, k)
            a = np.where(ws > 0, wa / np.where(ws > 0, ws, 1.0), 0.0)
            w = ws
        elif name in files:
            raise _size_error(name, files[name], a.shape, full, want, downsample)
        else:
            extra = (f" or {(full.height, full.width)} (the scene camera's, reduced by "
                     f"downsample {downsample})") if want != (full.height, full.width) else ""
            raise DifffogError(f"target '{name}': shape {a.shape}, expected (height, width) = "
                               f"{want}{extra}")
        if np.any(w < 0) or not np.all(np.isfinite(w)):
            raise DifffogError(f"weights '{name}': must be finite and >= 0")
        out_t[name], out_w[name] = np.where(w > 0, a, 0.0), w
    if sum(float(w.sum()) for w in out_w.values()) == 0:
        raise DifffogError("weights: every pixel has zero weight; nothing to fit")
    return out_t, out_w
