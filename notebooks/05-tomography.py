# ---
# jupyter:
#   jupytext:
#     text_representation:
#       extension: .py
#       format_name: percent
#       format_version: '1.3'
#       jupytext_version: 1.19.6
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # 05 — Density tomography: a cloud's density grid from six views
#
# The fog's density grid is a differentiable parameter of the sweep solver: the lattice maps
# the grid onto everything it derives from it (each cell's fog, the sun's path, the cameras'
# march, each exact hit's depth towards the sun) by fixed linear maps, so the gradient of an
# image loss with respect to every cell costs one adjoint light solve, whatever the number of
# cells. `difffog.fit_density` fits the grid to the images of several views: L-BFGS-B on the
# log of each cell, a smoothness prior on the cloud's shape (the squared gradient of the
# density at a fixed total mass, so that the mass is the images' alone) whose weight each fit
# chooses for itself (the balancing principle), space carving and a ladder of grids. Its light
# solve takes the sweep's sub-stepped scheme, the closest to Mitsuba at the clouds' edges.
#
# The shared case (`cloud-tomo`): a 32³ cloud (ζ = 36, γ = 4, optical depth up to ~7
# vertically and ~13 horizontally) over a ground quad, six 64×64 cameras. The targets are
# **Mitsuba 3's images** of the true scene (independent Monte Carlo, no inverse crime); the fit
# starts from `cloud-tomo-start`, a uniform box around the cloud.
#
# The size switch: `small` (what the test suite runs: the cloud averaged to 8³, two views at
# 16×16, a 10-node lattice, a few evaluations; about a minute on 2 CPU cores, mostly
# compiling) or `full` (the benchmark's settings, `benchmarks/tomography.py`: 8³ → 16³ → 32³,
# lattices 16 / 24 / 32; about 6½ minutes).

# %%
import os

SIZE = os.environ.get("DIFFFOG_NOTEBOOK_SIZE", "full")
if SIZE not in ("small", "full"):
    raise ValueError(f"DIFFFOG_NOTEBOOK_SIZE must be 'small' or 'full', got {SIZE!r}")
SMALL = SIZE == "small"
VIEWS = ["top", "view0"] if SMALL else ["top", "view0", "view1", "view2", "view3", "view4"]
GRID = 8 if SMALL else 32  # the estimate's cells along each axis
print(f"size {SIZE}: {len(VIEWS)} views, a {GRID}³ grid")

# %%
import dataclasses
import time
import warnings

import matplotlib.pyplot as plt
import numpy as np

import difffog as df
from difffog.study import references

truth_scene = df.load_scene("cloud-tomo")
start_scene = df.load_scene("cloud-tomo-start")
truth32 = np.asarray(truth_scene.fog.density, np.float64)
start32 = np.asarray(start_scene.fog.density, np.float64)


def block(g, n):
    """A cell-centred 32³ grid averaged down to n³ cells."""
    k = g.shape[0] // n
    return g.reshape(n, k, n, k, n, k).mean(axis=(1, 3, 5))


def box_mean(img, k):
    """An image averaged over k×k blocks."""
    h, w = img.shape
    return img.reshape(h // k, k, w // k, k).mean(axis=(1, 3))


truth = block(truth32, GRID) if SMALL else truth32
start = block(start32, GRID) if SMALL else start32
start = np.where(start > 0, start.max(), 0.0) if SMALL else start  # the box, uniform
PIX = 4 if SMALL else 1  # the small size's views are the references averaged 4×4
targets = {v: box_mean(np.asarray(references.reference("cloud-tomo", v)[0], np.float64), PIX)
           for v in VIEWS}
cams = tuple(dataclasses.replace(c, resolution=(c.width // PIX, c.height // PIX))
             for c in start_scene.cameras if c.name in VIEWS)
scene = start_scene.replace(fog=dataclasses.replace(start_scene.fog, density=start),
                            cameras=cams)
print("targets:", {v: t.shape for v, t in targets.items()})
print(f"truth: {np.count_nonzero(truth)} nonzero cells of {truth.size}, peak {truth.max():.2f}; "
      f"start: {np.count_nonzero(start)} cells at {start.max():.2f}")

# %% [markdown]
# ## 1. The targets and the truth
#
# Mitsuba's images of the true cloud, from the top (orthographic) and around it (perspective),
# and the truth's middle slices. The fit never sees the truth; it is here to judge the result.

# %%
fig, ax = plt.subplots(1, len(VIEWS), figsize=(2.6 * len(VIEWS), 2.8))
for a, v in zip(np.atleast_1d(ax), VIEWS):
    a.imshow(targets[v], cmap="gray")
    a.set_title(v)
    a.axis("off")
fig.suptitle("targets: Mitsuba 3's images of cloud-tomo")
fig.tight_layout()
plt.show()


def slices(grids, titles, suptitle):
    """The middle x, y and z slices of each grid (rows), on one colour scale."""
    vmax = max(float(g.max()) for g in grids)
    fig, ax = plt.subplots(len(grids), 3, figsize=(9, 2.9 * len(grids)), squeeze=False)
    for r, (g, t) in enumerate(zip(grids, titles)):
        n = g.shape
        for c, (cut, lab) in enumerate(((g[n[0] // 2], "x"), (g[:, n[1] // 2], "y"),
                                        (g[:, :, n[2] // 2], "z"))):
            im = ax[r, c].imshow(cut.T, origin="lower", vmin=0, vmax=vmax, cmap="magma")
            ax[r, c].set_title(f"{t}: middle {lab} slice", fontsize=9)
            ax[r, c].set_xticks([])
            ax[r, c].set_yticks([])
    fig.colorbar(im, ax=ax, shrink=0.8, label="density")
    fig.suptitle(suptitle)
    plt.show()


slices([truth, start], ["truth", "start"], "the truth and the start")

# %% [markdown]
# ## 2. The fit
#
# `fit_density` carves the support first (a pixel whose target matches the fog-free image
# within 2% sees clear sky or ground: a cell that such rays of two views cross through its
# middle is emptied), then runs L-BFGS-B
# level by level, each level started from the last one's estimate. The command line does the
# same: `difffog fit cloud-tomo-start --target top=top.exr ... --unknown fog.density --out DIR`.

# %%
if SMALL:
    settings = dict(grids=None, resolutions=(10,), downsample=(1,), max_steps=4, M=2,
                    supersample=1, settings={"scheme": "step"})
else:  # the defaults: grids 8³, 16³, 32³ at N = 16, 24, 32, images 1/4, 1/2, 1/1 (two rays
    # per target pixel side), the sub-stepped scheme, the shape prior from 3e-5 and balanced,
    settings = dict()  # 20 / 20 / 40 evaluations at most (per pass)
with warnings.catch_warnings():
    warnings.simplefilter("ignore", df.ThickStepWarning)
    fit = df.fit_density(scene, targets, start=start, progress=False, **settings)
print(f"{fit.result} in {fit.time_s:.0f} s")
for lv in fit.levels:
    print(f"  grid {lv['grid'][0]}³, N = {lv['resolution']}, images 1/{lv['downsample']}: "
          f"{lv['steps']} evaluations, loss {lv['loss']:.3g}, carved {lv['carved_cells']} cells, "
          f"first call (compile + 1 evaluation) {lv['compile_s']:.0f} s, level {lv['seconds']:.0f} s")
err0 = np.linalg.norm(start - truth) / np.linalg.norm(truth)
print(f"relative L2 error: start {err0:.3f} -> estimate {fit.relative_error(truth):.3f}")
print(f"total-mass bias: start {start.sum() / truth.sum() - 1:+.3f} -> estimate "
      f"{fit.mass_bias(truth):+.3f}")
bal = fit.levels[-1].get("balance")
if bal:  # the prior's weight chosen by the balancing principle at the final level
    print(f"prior weight {' -> '.join(f'{w:.3g}' for w in bal['prior_weights'])}; prior/data "
          f"at each pass's end {', '.join(f'{r:.2f}' for r in bal['shares'])} (aim "
          f"{bal['target']}; " + ("within the rule's band: one pass)" if len(bal["shares"]) == 1
                                    else "the final level ran again at the new weight)"))

# %%
slices([truth, fit.density], ["truth", "estimate"], "the estimate against the truth")

# %%
fig, ax = plt.subplots(1, 2, figsize=(10, 3.4))
hist = [h for h in fit.history if "loss" in h]
ax[0].semilogy([h["loss"] for h in hist], "o-", ms=3, label="loss")
ax[0].semilogy([h["data"] for h in hist], ".-", ms=3, label="images' misfit")
ax[0].semilogy([h["prior"] for h in hist], ".-", ms=3, label="prior")
for k in np.flatnonzero(np.diff([h["level"] for h in hist])):
    ax[0].axvline(k + 0.5, color="gray", lw=0.8)
ax[0].set_xlabel("evaluation (gray lines: the next grid level)")
ax[0].legend()
ax[0].set_title("convergence")
names = [f"{lv['grid'][0]}³" for lv in fit.levels]
first = [lv["compile_s"] for lv in fit.levels]
rest = [lv["seconds"] - lv["compile_s"] for lv in fit.levels]
ax[1].bar(names, first, label="first call (compile + 1 evaluation)")
ax[1].bar(names, rest, bottom=first, label="the other evaluations")
ax[1].set_ylabel("seconds")
ax[1].set_title("where the time goes, per level")
ax[1].legend(fontsize=8)
fig.tight_layout()
plt.show()

# %% [markdown]
# ## 3. One adjoint solve: the gradient for every cell
#
# The grid is a traced parameter (`df.with_density(params, grid)`), so the gradient of a loss
# with respect to every cell comes from reverse mode through the implicit light solve: one
# adjoint solve, whatever the number of cells. `fit.gradient(grid)` evaluates the fit's own
# loss (the images' relative misfit + the prior) and its gradient per unit density with the
# program the fit compiled; your own loss is a few lines:
#
# ```python
# model = df.forward_model(scene, "sweep", resolution=16)
# p = model.params()
# misfit = lambda g: sum(jnp.mean((img - targets[c]) ** 2) for c, img in
#                        model.images(df.with_density(p, g)).items())
# grad = jax.jit(jax.grad(misfit))(grid)   # one adjoint light solve for every cell
# ```
#
# Negative: more density there lowers the loss. (Carved cells, which the fit holds empty,
# show 0.)

# %%
t = time.perf_counter()
val0, g0 = fit.gradient(start)
val1, g1 = fit.gradient()
print(f"loss {val0:.3g} at the start, {val1:.3g} at the estimate; two gradients for "
      f"{np.count_nonzero(fit.support)} cells in {time.perf_counter() - t:.1f} s")
fig, ax = plt.subplots(2, 2, figsize=(7.5, 6.4))
n = g0.shape
for r, (g, name) in enumerate(((g0, "start"), (g1, "estimate"))):
    lim = float(np.abs(g).max()) or 1.0
    for c, (cut, lab) in enumerate(((g[n[0] // 2], "x"), (g[:, :, n[2] // 2], "z"))):
        im = ax[r, c].imshow(cut.T, origin="lower", cmap="RdBu_r", vmin=-lim, vmax=lim)
        ax[r, c].set_title(f"d loss / d density at the {name},\nmiddle {lab} slice", fontsize=9)
        ax[r, c].set_xticks([])
        ax[r, c].set_yticks([])
    fig.colorbar(im, ax=ax[r], shrink=0.8)
plt.show()

# %% [markdown]
# ## 4. The fitted images
#
# The estimate rendered at the last level's settings beside the targets: what the images say
# the cloud is. A residual at the noise level (the references' ~1–2%) plus the model's own
# error is all the images can tell; the optically thick core is weakly constrained by them,
# which is where the estimate and the truth part.

# %%
imgs, level_targets = fit.images()  # at the last level's lattice and image size
fig, ax = plt.subplots(3, len(VIEWS), figsize=(2.4 * len(VIEWS), 7), squeeze=False)
for c, v in enumerate(VIEWS):
    t_img = level_targets[v]
    f_img = imgs[v]
    vmax = float(max(t_img.max(), f_img.max()))
    ax[0, c].imshow(t_img, cmap="gray", vmin=0, vmax=vmax)
    ax[1, c].imshow(f_img, cmap="gray", vmin=0, vmax=vmax)
    r = ax[2, c].imshow(f_img - t_img, cmap="RdBu_r", vmin=-0.2 * vmax, vmax=0.2 * vmax)
    ax[0, c].set_title(v)
    for a in ax[:, c]:
        a.axis("off")
ax[0, 0].text(-0.1, 0.5, "target", transform=ax[0, 0].transAxes, rotation=90, va="center")
ax[1, 0].text(-0.1, 0.5, "fit", transform=ax[1, 0].transAxes, rotation=90, va="center")
ax[2, 0].text(-0.1, 0.5, "fit − target", transform=ax[2, 0].transAxes, rotation=90,
              va="center")
fig.colorbar(r, ax=ax[2], shrink=0.8)
plt.show()
rms = np.sqrt(np.mean(np.concatenate([(imgs[v] - level_targets[v]).ravel() for v in VIEWS]) ** 2))
bright = np.sqrt(np.mean(np.concatenate([level_targets[v].ravel() for v in VIEWS]) ** 2))
print(f"residual RMS {rms / bright:.1%} of the targets' RMS")

# %% [markdown]
# ## 5. Where this stands
#
# The run above uses today's defaults (stop 51: the sub-stepped scheme, the shape prior with
# its weight balanced, the carving that keeps the cloud, two rays per side of a target pixel,
# the line search bounded at 100 mean free paths per cell). The benchmark (`python
# benchmarks/tomography.py`, the same settings) reached a relative L2 error of 0.140 with the
# total mass within 1.6% (from a uniform start at 1.46 and +349%) in 338 s; the issue's
# aim is 15% and 2%. On three clouds of our own with Mitsuba images (`data_synthetic/`) the
# same defaults give 0.193 / +3.7% (`cloud-tomo-b`), 0.198 / +5.9% (`-c`) and 0.197 / −1.1%
# (`-d`, a flat deck made after the defaults were chosen, to check them): short of 15%. From
# their own noise-free images b and c come to 0.156 and 0.154, so what is left there is mostly
# not the forward model: six 64² views do not pin down a cloud's cell-scale structure, and the
# smoothness prior fills it in smoothly. From the sweep's own images at N = 48 the shared cloud
# comes to 0.116, not the 10%. The defaults until stop 50 (the step scheme and the
# plain squared gradient, `settings={"scheme": "step"}, prior="smooth"`) were faster (221 s)
# and as close here (0.142), but that prior pulls every fit's mass down (b, c, d came out 3–11%
# thin) and only cancelled the step scheme's own bias on this cloud (docs/tomography.md). A fit stopped early keeps a
# checkpoint: `fit_density(..., checkpoint=PATH)` and `resume=True` (or
# `difffog fit ... --resume`) go on from it.
