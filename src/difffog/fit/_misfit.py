"""Goodness of fit: does the model explain the target images as well as the noise and its own
error allow, and if not, how far the unexplained misfit can move the estimates.

A fit's standard errors assume the residual is white noise.  When something the fit holds fixed
differs from the images (the sun's angle, the sky, an albedo that is not an unknown, the
camera, the geometry), the unknowns absorb part of it and the residual keeps the rest, as
structure: the estimates are biased far beyond their standard errors, and the fit still
converges.  Measured on fog-balls' Mitsuba images (the README's API example; ``python
benchmarks/misfit.py``): with the sun 8° off, the balls' albedo 0.6 instead of 0.8 or the
sky twice as bright, the fits converged 4–28 total uncertainties from the truth, their
residuals 2–9% of the images' mean against 0.6–1.3% for the right scene.

Per camera (its weighted pixels), the residual's RMS relative to the target's mean, ρ, is held
against what the fit expects: ε² = σ² + λ² + f², σ the target's own noise (estimated from the
image, :func:`noise_sigma`), λ the model's own error in the images (the finer model's images
at the estimate, the doubled lattice and for the sweep M + 1, against the fit's, × N_f/(N_f − N):
first order in the voxel size; less its part that the unknowns absorb, which leaves no
residual) and f the brightness floor (not projected: it stands for an error of unknown shape).  The share of the residual's variance that
they do not explain, κ = max(0, 1 − ε²/ρ²), is the misfit; above ``MISFIT_RATIO`` (ρ > 2ε) the
fit warns (:class:`MisfitWarning`).  Its part in each estimate's model error is the root sum of
squares of two shifts:

* the misfit as a brightness bias: each camera's images ρ·√κ too bright, one camera at a time,
  as the brightness floor (what a biased exposure or a wrong irradiance looks like);
* the misfit where it lies: the estimates' spread over the images' regions, a cluster-robust
  (sandwich) covariance (JᵀJ)⁻¹ (Σ_b κ_b g_b g_bᵀ) (JᵀJ)⁻¹ · G/(G − 1) over G tiles b of
  every camera (``TILES`` × ``TILES`` each), g_b = J_bᵀ r_b: how much the estimates depend on
  which part of the images they come from, which a misplaced shadow or a wrong albedo makes
  large and white noise does not.

A misfit that the unknowns absorb entirely leaves no residual and cannot be seen this way: the
warning is a necessary check, not a sufficient one.
"""

from __future__ import annotations

import math

import numpy as np

#: the fit warns when a camera's residual RMS is more than this many times what noise, the
#: lattice and the brightness floor explain
MISFIT_RATIO = 2.0
#: below this residual (relative to the image mean) nothing is called a misfit: a fit stops
#: within its tolerances (rtol = atol = 1e-4 on the unknowns and the residual), which leave a
#: residual of that order where the model fits exactly
RESOLVED = 1e-3
#: tiles per image side for the misfit's regional spread (16 per camera)
TILES = 4


class MisfitWarning(UserWarning):
    """The fitted model leaves a residual larger than the images' noise and the model's own
    error explain: something the fit holds fixed differs from the images, and the estimates
    can be biased.  Their uncertainty includes the misfit (``model_error_parts["misfit"]``)."""


def noise_sigma(image) -> float:
    """The standard deviation of white noise in ``image`` (2-D), from the image alone:
    Immerkær's estimator (the image convolved with the product of two second differences,
    [1, −2, 1] ⊗ [1, −2, 1], whose response to shading that is a sum of a function of x and one
    of y is 0 and to white noise of σ is 6σ), with the median absolute value instead of the
    mean so that edges and silhouettes do not count (×1.4826: the MAD of a normal variable).
    Noise correlated between neighbouring pixels (a demosaiced photograph's) reads smaller than
    it is.  0 for an image smaller than 3×3."""
    a = np.asarray(image, np.float64)
    if a.ndim != 2 or min(a.shape) < 3:
        return 0.0
    c = (a[:-2, :-2] - 2 * a[:-2, 1:-1] + a[:-2, 2:]
         - 2 * a[1:-1, :-2] + 4 * a[1:-1, 1:-1] - 2 * a[1:-1, 2:]
         + a[2:, :-2] - 2 * a[2:, 1:-1] + a[2:, 2:])
    c = c[np.isfinite(c)]
    return float(1.4826 * np.median(np.abs(c)) / 6.0) if c.size else 0.0


def _rms(v, w2) -> float:
    s = float(np.sum(w2))
    return math.sqrt(float(np.sum(w2 * v * v)) / s) if s > 0 else 0.0


def per_camera(st, y, target, sqrt_w, change, lattice_factor: float, floor: float, J,
               scale: float) -> dict:
    """{camera: {residual, noise, lattice, floor, expected, ratio, unexplained}} (relative to
    the camera's weighted target mean): ``y`` the fit's images at the estimate, ``change`` the
    finer model's images there less ``y``, in the units of the residual √w·(y − target)/
    ``scale``, whose Jacobian is ``J``.  The lattice error λ is that change × ``lattice_factor``,
    less what the unknowns absorb (its part in the span of J's columns, which the fit takes up
    by moving the estimates, the correction's business, and leaves no residual)."""
    change = change - J @ np.linalg.lstsq(J, change, rcond=None)[0]
    out, off = {}, 0
    for name in st.names:
        size = st.tgt[name].size
        sl = slice(off, off + size)
        off += size
        w2 = sqrt_w[sl] ** 2
        if not np.sum(w2) > 0:
            continue
        mean = float(np.sum(w2 * target[sl]) / np.sum(w2))
        if not mean > 0:
            continue
        rho = _rms(y[sl] - target[sl], w2) / mean
        sigma = noise_sigma(st.tgt[name]) / mean
        lam = scale * math.sqrt(float(np.sum(change[sl] ** 2) / np.sum(w2))) / mean
        lam *= lattice_factor
        expected = max(math.sqrt(sigma ** 2 + lam ** 2 + floor ** 2), RESOLVED)
        out[name] = dict(residual=rho, noise=sigma, lattice=lam, floor=floor,
                         expected=expected,
                         ratio=rho / expected if expected > 0 else math.inf,
                         unexplained=max(0.0, 1.0 - (expected / rho) ** 2) if rho > 0 else 0.0)
    return out


def _tiles(shape, offset: int, k: int = TILES):
    h, w = shape
    idx = np.arange(h * w).reshape(h, w) + offset
    for rows in np.array_split(np.arange(h), min(k, h)):
        for cols in np.array_split(np.arange(w), min(k, w)):
            yield idx[np.ix_(rows, cols)].ravel()


def regional_spread(st, J, r, cams: dict) -> np.ndarray:
    """The unconstrained unknowns' covariance from the misfit where it lies: the cluster-robust
    sandwich over every camera's tiles, each tile's score J_bᵀ r_b weighted by its camera's
    unexplained share (``cams``); zeros where no camera has a misfit."""
    n = J.shape[1]
    meat, tiles, off = np.zeros((n, n)), 0, 0
    for name in st.names:
        shape = st.tgt[name].shape
        kappa = cams.get(name, {}).get("unexplained", 0.0)
        for b in _tiles(shape, off):
            g = J[b].T @ r[b]
            meat += kappa * np.outer(g, g)
            tiles += 1
        off += st.tgt[name].size
    if tiles < 2 or not np.any(meat):
        return np.zeros((n, n))
    bread = np.linalg.pinv(J.T @ J)
    return bread @ meat @ bread * tiles / (tiles - 1)


def message(cams: dict) -> str | None:
    """The warning for the cameras whose residual is more than ``MISFIT_RATIO`` times the
    expected, or None."""
    bad = {n: c for n, c in cams.items() if c["ratio"] > MISFIT_RATIO}
    if not bad:
        return None
    said = "; ".join(
        f"{n} {c['residual']:.1%} of its mean, {c['ratio']:.1f}× the {c['expected']:.1%} "
        f"that noise ({c['noise']:.1%}), the lattice ({c['lattice']:.1%})"
        f" and the brightness floor ({c['floor']:.1%}) explain" for n, c in bad.items())
    return (f"the model does not explain the images: residual RMS {said}. Something the fit "
            f"holds fixed differs from the images (the sun, the sky, an albedo that is not an "
            f"unknown, a camera, the geometry, a mask): the estimates can be biased; their "
            f"uncertainty includes the misfit (model_error_parts 'misfit'), and a misfit the "
            f"unknowns absorb cannot be seen. Look at the residual images")
