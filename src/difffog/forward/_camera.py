"""Cameras, shared by both forward models: a camera's frame, its box-filtered sub-pixel rays
(host, NumPy, once per camera) and the Henyey–Greenstein phase of light scattered towards it.

Conventions (``difffog/data/scenes/SCHEMA.md``): z is up; images are (H, W), row 0 at the top,
column 0 at the left; a perspective ``fov_deg`` is the full *horizontal* field of view; pixels
are box filtered (the mean over the pixel footprint), which the regular s×s sub-pixel grid of
:func:`camera_rays` approximates.  ``sun_dir`` points *towards* the sun; the light travels
along ``-sun_dir`` and reaches the camera travelling along ``-d`` for a camera ray ``d``, so the
scattering angle has ``cos θ = dot(sun_dir, d)`` (looking into the sun is forward scattering,
where a g > 0 phase function peaks).
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from .._errors import SceneError
from .._numerics import FOUR_PI
from ..scene._description import Camera

# --------------------------------------------------------------------------------------------
# rays (host, NumPy)
# --------------------------------------------------------------------------------------------
def camera_basis(camera: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(forward, right, true_up) unit vectors of a camera, float64 (3,) each.

    forward = normalize(look_at - position), right = normalize(forward × up),
    true_up = right × forward.
    """
    pos = np.asarray(camera.position, np.float64)
    fwd = np.asarray(camera.look_at, np.float64) - pos
    n = np.linalg.norm(fwd)
    if not n > 0:
        raise SceneError(f"camera '{camera.name}': look_at equals position {tuple(pos)}; "
                         "move look_at away from the camera")
    fwd = fwd / n
    right = np.cross(fwd, np.asarray(camera.up, np.float64))
    n = np.linalg.norm(right)
    if not n > 1e-12:
        raise SceneError(f"camera '{camera.name}': up {tuple(camera.up)} is parallel to the "
                         "viewing direction; choose an up vector not along look_at - position")
    right = right / n
    return fwd, right, np.cross(right, fwd)


def _subpixel_ndc(width: int, height: int, s: int) -> tuple[np.ndarray, np.ndarray]:
    """NDC coordinates (H, W, s²) of the s×s sub-cell centres of every pixel.

    x_ndc ∈ [-1, 1] runs left→right, y_ndc ∈ [-1, 1] bottom→top (row 0 is the top); the
    sub-samples of a pixel are ordered row-major (sub-row, then sub-column).
    """
    sub = (np.arange(s) + 0.5) / s
    x_pix = np.arange(width)[None, :, None, None] + sub[None, None, None, :]  # (1, W, 1, s)
    y_pix = np.arange(height)[:, None, None, None] + sub[None, None, :, None]  # (H, 1, s, 1)
    x_ndc = 2.0 * x_pix / width - 1.0
    y_ndc = 1.0 - 2.0 * y_pix / height
    shape = (height, width, s, s)
    return (np.broadcast_to(x_ndc, shape).reshape(height, width, s * s),
            np.broadcast_to(y_ndc, shape).reshape(height, width, s * s))


def camera_rays(camera: Camera, supersample: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Deterministic stratified rays of a camera.

    Returns ``(origins, directions)``, float64 NumPy arrays of shape (H, W, S, 3) with
    S = supersample², the sub-samples of a pixel at the centres of a regular s×s grid of
    sub-cells (row-major), so that the mean over S approximates the box-filtered pixel.
    Directions are unit vectors.  Perspective: origin = position, direction through the image
    point ``forward + x_ndc·tan(fov/2)·right + y_ndc·tan(fov/2)·(H/W)·true_up``.
    Orthographic: origin = position + x_ndc·(w/2)·right + y_ndc·(h/2)·true_up, direction =
    forward, with (w, h) = extent.
    """
    s = int(supersample)
    if s < 1:
        raise ValueError(f"supersample must be a positive integer, got {supersample!r}")
    width, height = (int(v) for v in camera.resolution)
    if width < 1 or height < 1:
        raise SceneError(f"camera '{camera.name}': resolution {camera.resolution} must be "
                         "positive [width, height]")
    x, y = _subpixel_ndc(width, height, s)
    return rays_at(camera, x, y)


def hammersley_ndc(camera: Camera, pixels, n: int) -> tuple[np.ndarray, np.ndarray]:
    """NDC coordinates (P, n) of n Hammersley points in each of the given pixels (P, 2) as
    (row, column): x = (i + 1/2)/n, y = the base-2 radical inverse of i (shifted by 1/2n).
    Both projections are stratified into n bins, so an axis-aligned edge's coverage is right to
    1/n (a regular s×s grid: 1/2s), and any straight edge's to O(log n / n)."""
    width, height = (int(v) for v in camera.resolution)
    pixels = np.asarray(pixels, np.int64).reshape(-1, 2)
    i = np.arange(n)
    rad = np.zeros(n)
    f, k = 0.5, i.copy()
    while k.any():
        rad += f * (k & 1)
        k >>= 1
        f *= 0.5
    sx = (i + 0.5) / n
    sy = (rad + 0.5 / n) % 1.0
    x = 2.0 * (pixels[:, 1:2] + sx[None, :]) / width - 1.0
    y = 1.0 - 2.0 * (pixels[:, 0:1] + sy[None, :]) / height
    return x, y


def rays_at(camera: Camera, x, y) -> tuple[np.ndarray, np.ndarray]:
    """Rays (origins, unit directions), shape x.shape + (3,), of a camera through the image
    points of NDC coordinates x (left→right) and y (bottom→top) in [-1, 1]; see
    :func:`camera_rays`."""
    width, height = (int(v) for v in camera.resolution)
    fwd, right, up = camera_basis(camera)
    x, y = np.asarray(x, np.float64)[..., None], np.asarray(y, np.float64)[..., None]
    pos = np.asarray(camera.position, np.float64)
    if camera.kind == "perspective":
        if camera.fov_deg is None or not 0.0 < camera.fov_deg < 180.0:
            raise SceneError(f"camera '{camera.name}': perspective fov_deg must lie in "
                             f"(0, 180), got {camera.fov_deg!r}")
        tx = math.tan(math.radians(camera.fov_deg) / 2.0)
        ty = tx * height / width
        d = fwd + x * tx * right + y * ty * up
        d = d / np.linalg.norm(d, axis=-1, keepdims=True)
        o = np.broadcast_to(pos, d.shape).copy()
    elif camera.kind == "orthographic":
        if camera.extent is None or not (camera.extent[0] > 0 and camera.extent[1] > 0):
            raise SceneError(f"camera '{camera.name}': orthographic extent must be positive "
                             f"[width, height], got {camera.extent!r}")
        ew, eh = (float(v) for v in camera.extent)
        o = pos + x * (ew / 2.0) * right + y * (eh / 2.0) * up
        d = np.broadcast_to(fwd, o.shape).copy()
    else:
        raise SceneError(f"camera '{camera.name}': unknown kind {camera.kind!r}; use "
                         "'perspective' or 'orthographic'")
    return o, d


def forward_peak_kernel(cos_theta, width, xp=jnp):
    """K in [0, 1]: 1 − (1 − cos θ)/width, 0 beyond, around the forward direction (cos θ = 1);
    ``width`` = 1 − cos θ_w.  The window of the Henyey–Greenstein forward peak that the sweep's
    sun beam keeps: the beam's light scatters with (1 − c·K)·p (``sweep._solver._cell_phase``).
    ``xp``: jax.numpy (traced) or NumPy (the slab reading, ``study._slab``)."""
    return xp.maximum(0.0, 1.0 - (1.0 - cos_theta) / width)


def hg_phase(cos_theta, g):
    """Henyey–Greenstein phase function, normalised to 1 over the sphere (units 1/sr).

    p(cos θ) = (1 - g²) / (4π (1 + g² - 2 g cos θ)^{3/2}); g > 0 peaks at cos θ = 1 (forward).
    """
    cos_theta = jnp.asarray(cos_theta)
    g = jnp.asarray(g)
    denom = 1.0 + g * g - 2.0 * g * cos_theta
    return (1.0 - g * g) / (FOUR_PI * denom * jnp.sqrt(denom))


