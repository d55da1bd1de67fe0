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
# # 04 — The papers' figures
#
# The two papers behind difffog show their methods on a handful of scenes. This notebook re-makes
# those figures with difffog, with the papers' settings where they state them (iterations) and the
# converged answer beside them, so that the difference is visible.
#
# * Langer, Breton & Zucker, *Massively Parallel Radiosity in the Presence of Multiple Isotropic
#   Volume Scattering*: Fig. 4 (a ring in an open box, through the roof from four directions)
#   and Fig. 5 (three balls in fog with their shadow tubes) — the sweep solver.
# * Zhang & Crawfis, *Shadows and Soft Shadows with Participating Media Using Splatting*:
#   Figs. 1, 2, 4 (clouds with no / forward / forward and back multiple scattering) and
#   Figs. 8, 16 (hard and soft shadows of polygons on volumes) — the splat solver
#   (`df.forward_model(scene, "splat")`, a `df.SplatModel`).

# %%
import os

# "small": what the test suite runs (quick checks: minutes on 2 CPU cores, mostly compiling);
# "full": the default, for people (the times are in notebooks/README.md)
SIZE = os.environ.get("DIFFFOG_NOTEBOOK_SIZE", "full")
if SIZE not in ("small", "full"):
    raise ValueError(f"DIFFFOG_NOTEBOOK_SIZE must be 'small' or 'full', got {SIZE!r}")
SMALL = SIZE == "small"
N = 24 if SMALL else 64  # lattice nodes along the longest side of the domain
M = 2 if SMALL else 3  # direction half-width: (2M+1)^2 directions per cube face
TOL = 1e-2 if SMALL else 1e-4  # the solver's estimated remaining relative error
print(f"size {SIZE}: N = {N}, M = {M}, tol = {TOL:g}")

# %%
import dataclasses
import math
import time

import equinox as eqx
import numpy as np
from IPython.display import display

import difffog as df
from difffog import plot

RES = 64 if SMALL else 128  # camera pixels (the cost is in the light solve, not here)

# %% [markdown]
# ## Langer et al., Fig. 4: a ring floating in a box, through the roof
#
# *"A ring floating in a box is viewed through the top via parallel projection from four
# different directions. No volume scattering was present. The albedo of all surfaces was 0.9.
# The light source had two components, ambient and directed, both of which entered the box
# through the open roof. The ambient component was a uniform hemispheric sky, and the directed
# component was oblique, from the left. Twelve iterations were used."*
#
# The built-in `ring-box` scene is that set-up (sky 1 W m⁻² sr⁻¹, sun 2 W m⁻² at zenith 35°
# from −x). Four orthographic cameras replace its own: tilted 20° from the vertical, from the four
# sides, all aimed at the middle of the open roof, so each sees the ring through it (and the
# outside of the nearest wall below the roof's edge).

# %%
ring_scene = df.load_scene("ring-box")
roof = np.array([0.5, 0.5, 1.0])  # the middle of the open roof


def roof_camera(name, azimuth_deg, tilt_deg=20.0):
    """An orthographic camera above the roof, tilted from the vertical towards azimuth."""
    a, t = math.radians(azimuth_deg), math.radians(tilt_deg)
    toward = np.array([math.sin(t) * math.cos(a), math.sin(t) * math.sin(a), math.cos(t)])
    return df.Camera(name=name, kind="orthographic", position=tuple(roof + 0.5 * toward),
                     look_at=tuple(roof), up=(0.0, 0.0, 1.0), extent=(1.2, 1.2),
                     resolution=(RES, RES))


# from +x, +y, −x, −y (camera names take letters, digits, '-' and '_')
views = [roof_camera(f"from-{side}", az) for side, az in
         [("east", 0.0), ("north", 90.0), ("west", 180.0), ("south", 270.0)]]
ring_scene = dataclasses.replace(ring_scene, cameras=tuple(views))


light_of = eqx.filter_jit(lambda model, p: model.light(p))
images_of = eqx.filter_jit(lambda model, light, p: model.images_from(light, p))


def paper_and_converged(scene, iterations):
    """Light and images after the paper's number of Jacobi iterations and converged.

    Both with the paper's method, plain Jacobi iteration (difffog's default is GMRES, whose
    iterations are not bounces of light).  One model (one lattice, one compiled camera pass)
    serves both: a model is a pytree, so ``eqx.tree_at`` swaps in a solver that runs exactly
    the paper's iterations (tol 0) and keeps everything the host prepared."""
    model = df.forward_model(scene, "sweep", accuracy=None, resolution=N, M=M, tol=TOL,
                             max_iterations=500, method="jacobi")
    paper = eqx.tree_at(lambda m: m.solver, model,
                        df.SweepSolver(M=M, max_iterations=iterations, tol=0.0, method="jacobi"))
    p = model.params()
    out = {}
    for key, m in [("paper", paper), ("converged", model)]:
        t = time.perf_counter()
        light = light_of(m, p)
        images = {k: np.asarray(v) for k, v in images_of(model, light, p).items()}
        out[key] = (light, images)
        print(f"{scene.title}, {key}: {int(light.iterations)} iterations, "
              f"{time.perf_counter() - t:.1f} s (compilation included)")
    return model, out


ring_model, ring = paper_and_converged(ring_scene, 12)  # the paper used twelve iterations
plot.image_grid(ring["paper"][1], ncols=4,
                suptitle=f"Langer et al. Fig. 4 with difffog: 12 iterations, N = {N}, M = {M}")

# %% [markdown]
# How far are twelve iterations from the converged light? With albedo 0.9 everywhere each
# bounce keeps most of the light, so the Jacobi iteration contracts slowly (about 0.8 per
# iteration at N = 64: the slope below) and twelve iterations leave the inside of the box a few
# per cent too dark, most of all on the floor and low on the walls, where light arrives after
# several bounces. The paper's images were not converged either.

# %%
light, images = ring["converged"]
display(plot.image_grid(images, ncols=4, suptitle="converged"))
fig = plot.convergence(light, tol=TOL, label="ring-box, converged run")
fig.axes[0].axvline(12, color="grey", ls="--", lw=1, label="the paper's 12 iterations")
fig.axes[0].legend(fontsize=8)
display(fig)
name = views[2].name
plot.error_map(ring["paper"][1][name], images[name],
               title=f"12 iterations against converged, view {name}")

# %% [markdown]
# ## Langer et al., Fig. 5: three balls in fog and their shadow tubes
#
# *"Three balls are shown floating in a box that is filled with homogeneous fog. The scene is
# illuminated by a directed light source that is from above but slightly oblique. The shadows
# cast by the balls are visible both in space (as tubes) and on the surface. Observe that the
# deepest ball is the darkest since light is absorbed as it passes through the fog. Five
# iterations of Coordinate Evolution were used."*
#
# The built-in `fog-balls` scene (ζ = 2, γ = 0.5 per unit, sun at zenith 20°), rendered after the
# paper's five iterations and converged.

# %%
balls_scene = df.load_scene("fog-balls")
balls_model, balls = paper_and_converged(balls_scene, 5)  # the paper used five iterations
display(plot.image_grid({f"5 iterations / {k}": v for k, v in balls["paper"][1].items()}
                        | {f"converged / {k}": v for k, v in balls["converged"][1].items()},
                        ncols=2))
# fog of albedo 0.8 converges faster than the ring's box: five iterations are closer
plot.error_map(balls["paper"][1]["oblique"], balls["converged"][1]["oblique"],
               title="5 iterations against converged, oblique view")

# %% [markdown]
# The tubes: the uncollided sunlight in vertical slices through each ball's centre. Each ball
# casts a shadow tube slanted along the sun; the lower balls sit in the upper ones' fog, and
# the floor carries all three shadows.

# %%
lat = balls_model.lattice
spheres = [(i, s) for i, s in enumerate(balls_scene.shapes) if s.kind == "sphere"]
iy = [int(np.floor((s.center[1] - lat.origin[1]) / lat.h)) for _, s in spheres]
plot.lattice_slices(lat, np.asarray(balls["converged"][0].sun_fluence), axis="y", index=iy,
                    label="uncollided sun F·T (W m⁻²)", ncols=3)

# %% [markdown]
# *"The deepest ball is the darkest"*: the mean radiosity B (the Lambertian exitant radiance)
# over each ball's surface nodes.

# %%
B = np.asarray(balls["converged"][0].radiosity)
shell = lat.node_type == 1  # SURFACE
for i, s in sorted(spheres, key=lambda x: -x[1].center[2]):
    mine = shell & (lat.material == i)
    print(f"{s.name:10s} centre height {s.center[2]:.2f}: mean radiosity "
          f"{B[mine].mean():.3f} W m⁻² sr⁻¹ over {mine.sum()} surface nodes")

# %% [markdown]
# ## Zhang & Crawfis, Figs. 1, 2, 4: a cloud with no, forward, and forward + back scattering
#
# Their Figs. 1, 2 and 4 show the same clouds with no multiple scattering (attenuation and
# single scattering only), with multiple forward scattering, and with forward and back
# scattering. The built-in `cloud-plane` scene's cloud (ζ = 60, γ = 0.6 per unit, a strongly
# forward-scattering phase, g = 0.85) without its airplane and ground, seen from the side,
# lit by a sun 60° from the zenith, once from behind the cloud and once from behind the viewer.
# `similarity=False` keeps the paper's kernels (the Henyey–Greenstein phase of g = 0.85 for
# the scattered light; the default `similarity=True` is the more accurate δ-scaled variant).
# `forward_scatter` and `back_scatter` switch the paper's two multiple scattering terms.

# %%
SPLAT_N = 16 if SMALL else 48  # the splatted voxels along the longest side
PX = 64 if SMALL else 160  # camera width in pixels
side = df.Camera(name="side", kind="perspective", position=(0.5, -0.9, 0.45),
                 look_at=(0.5, 0.5, 0.45), up=(0.0, 0.0, 1.0), fov_deg=45.0,
                 resolution=(PX, PX * 3 // 4))
kernels = {"no multiple scattering (Fig. 1)": {"forward_scatter": False, "back_scatter": False},
           "multiple forward (Fig. 2)": {"forward_scatter": True, "back_scatter": False},
           "forward + back (Fig. 4)": {"forward_scatter": True, "back_scatter": True}}
lights = {"sun behind the cloud": 90.0, "sun behind the viewer": -90.0}  # sun azimuth (deg)
if SMALL:  # the test suite: one light runs the same code
    lights = {"sun behind the cloud": 90.0}
clouds, ratio = {}, {}
for light, azimuth in lights.items():
    sc = df.load_scene("cloud-plane", ["sun.zenith_deg=60", f"sun.azimuth_deg={azimuth}"])
    sc = sc.replace(shapes=(), cameras=(side,))  # the cloud alone
    imgs = {}
    for title, kw in kernels.items():
        model = df.forward_model(sc, "splat", accuracy=None, resolution=SPLAT_N,
                                 similarity=False, **kw)
        imgs[title] = np.asarray(model()["side"])
    # which pixels see the cloud: those that change when the fog is removed
    p0 = df.set_param(df.set_param(model.params(), sc, "fog.scattering", 0.0),
                      sc, "fog.absorption", 0.0)
    clear = np.asarray(model(p0)["side"])
    none = imgs["no multiple scattering (Fig. 1)"]
    mask = np.abs(none - clear) > 0.02 * float(clear.max())
    clouds[light] = imgs
    ratio[light] = {k: float(v[mask].mean() / none[mask].mean()) for k, v in imgs.items()}
    display(plot.image_grid(imgs, ncols=3, suptitle=f"cloud-plane's cloud, {light} "
                            f"(splat, N = {SPLAT_N}, the paper's kernels)"))

# %% [markdown]
# How much brighter the cloud's pixels get when each multiple scattering term is switched on,
# relative to single scattering alone. Lit from behind, forward scattering carries the light
# on towards the viewer, so the cloud brightens most (the paper's Fig. 2 against Fig. 1); lit
# from behind the viewer, light has to turn round to come back, which forward scattering
# cannot do, and back scattering adds a little (Fig. 4).

# %%
import matplotlib.pyplot as plt

print("cloud pixels' mean radiance relative to single scattering alone:")
print(f"{'':24s}{'none (Fig. 1)':>15s}{'forward (Fig. 2)':>18s}{'+ back (Fig. 4)':>17s}")
for light in lights:
    print(f"{light:24s}" + "".join(f"{ratio[light][k]:{w}.3f}"
                                    for k, w in zip(kernels, (15, 18, 17))))
fig, ax = plt.subplots(figsize=(6.4, 3.2), layout="constrained")
w = 0.38
for j, light in enumerate(lights):
    ax.bar(np.arange(3) + (j - 0.5) * w, [ratio[light][k] for k in kernels], w, label=light)
ax.set_xticks(np.arange(3), [k.replace(" (", "\n(") for k in kernels], fontsize=8)
ax.axhline(1.0, color="k", lw=0.8)
ax.set_ylabel("mean cloud radiance / single scattering's")
ax.set_title(f"cloud brightness by scattering term (splat, N = {SPLAT_N})", fontsize=9)
ax.legend(fontsize=8)
display(fig)
plt.close(fig)
# the paper's point: multiple forward scattering brightens a back-lit cloud
assert ratio["sun behind the cloud"]["multiple forward (Fig. 2)"] > 1.05

# %% [markdown]
# ## Zhang & Crawfis, Figs. 8, 11, 16: hard and soft shadows
#
# A point sun casts hard shadows; a sun of finite angular radius a penumbra that widens with
# the distance between the occluder and what it shades. difffog's scenes give the sun an
# `angular_radius_deg` (0 by default: a point). Here the same scenes with the sun's radius set
# to 4° through the `--set`-style override, `df.apply_overrides(scene,
# ["sun.angular_radius_deg=4"])` — on the command line:
# `difffog render cloud-plane --solver splat --set sun.angular_radius_deg=4 --out out`.
# The airplane shades the cloud and the ground (its wings are 0.8 above the ground); the ring
# inside the translucent cube sits 0.35 above it, so its penumbra is narrower.

# %%
shadow_cases = [("cloud-plane", "the airplane on the cloud and the ground"),
                ("translucent-cube", "the ring in the cube")]
if SMALL:  # the test suite: one scene runs the same code
    shadow_cases = shadow_cases[1:]
pairs = {}
for name, what in shadow_cases:
    base = df.load_scene(name)
    cam = dataclasses.replace(base.camera("oblique"), resolution=(PX, PX * 3 // 4))
    base = base.replace(cameras=(cam,))
    pair = {}
    for radius in (0.0, 4.0):
        sc = df.apply_overrides(base, [f"sun.angular_radius_deg={radius}"])
        model = df.forward_model(sc, "splat", accuracy=None, resolution=SPLAT_N,
                                 soft_shadows=radius > 0)
        pair[f"sun radius {radius:g}°"] = np.asarray(model()["oblique"])
    pairs[name] = pair
    display(plot.image_grid(pair, ncols=2, suptitle=f"{name}: {what}, hard and soft shadows"))

# %% [markdown]
# A profile across each shadow, along the image row where the hard and the soft shadows differ
# most: the soft shadow's edge is spread over more pixels, and its core is less dark.

# %%
fig, axes = plt.subplots(1, 2, figsize=(10, 3.3), layout="constrained")
for ax, (name, pair) in zip(axes, pairs.items()):
    hard, soft = pair.values()
    row = int(np.argmax(np.abs(hard - soft).sum(axis=1)))
    for (label, img), color in zip(pair.items(), ["k", "tab:orange"]):
        ax.plot(img[row], lw=1.2, label=label, color=color)
    ax.set_xlabel("image column (pixel)")
    ax.set_ylabel(f"radiance ({plot.RADIANCE_UNIT})")
    ax.set_title(f"{name}: row {row} of the oblique view", fontsize=9)
    ax.legend(fontsize=8)
    print(f"{name}: the two differ by up to {np.abs(hard - soft).max():.3f} "
          f"{plot.RADIANCE_UNIT} (row {row}); mean radiance {hard.mean():.4f} hard, "
          f"{soft.mean():.4f} soft")
display(fig)
plt.close(fig)
