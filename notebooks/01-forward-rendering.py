# ---
# jupyter:
#   jupytext:
#     text_representation:
#       extension: .py
#       format_name: percent
#       format_version: '1.3'
#       jupytext_version: 1.19.7
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # 01 — Forward rendering
#
# Load one of the built-in scenes, look at the lattice the solver runs on, render it with the
# sweep solver (Langer, Breton & Zucker), compare the images with the independent Mitsuba 3
# references, and move sliders for the fog and the light.
#
# Everything runs on a CPU. The size switch below picks the lattice: `small` (24 nodes, what
# the test suite runs) or `full` (64 nodes, the default). Set `DIFFFOG_NOTEBOOK_SIZE=small`
# before starting Jupyter for a quick pass.

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
import time

import numpy as np
from IPython.display import display

import difffog as df
from difffog import plot
from difffog.study.references import reference, references_dir

# %% [markdown]
# ## 1. The scene
#
# `fog-balls`: three balls floating in a box of homogeneous fog with an open roof, lit by an
# oblique sun and a dim sky (after Langer et al., Fig. 5). Lengths are in scene units; the fog's
# scattering ζ and absorption γ are per unit length. `df.param_paths` lists what a fit (or a
# slider) can change without rebuilding anything.

# %%
scene = df.load_scene("fog-balls")
d, fog, sun = scene.domain, scene.fog, scene.sun
print(f"{scene.title}: domain {d.min} .. {d.max}, boundary {d.boundary}")
print(f"fog: ζ = {fog.scattering}, γ = {fog.absorption} per unit length, "
      f"single-scattering albedo {fog.single_scattering_albedo:.2f}")
print(f"sun: {sun.irradiance} W m⁻² from zenith {sun.zenith_deg}°, "
      f"azimuth {sun.azimuth_deg}°; "
      f"sky {scene.sky.radiance} W m⁻² sr⁻¹")
for s in scene.shapes:
    print(f"  shape {s.name:10s} {s.kind:9s} albedo {s.albedo}")
print("cameras:", ", ".join(c.name for c in scene.cameras))
print("parameters:", ", ".join(df.param_paths(scene)))

# %% [markdown]
# ## 2. The lattice
#
# A forward model, here the sweep's (`df.forward_model(scene, "sweep", ...)`, a `df.SweepModel`),
# voxelizes the scene once when it is built (on the host, NumPy): each node is FREE (light travels
# and scatters there), SURFACE (a shell M nodes thick around the solids, where light is reflected)
# or SOLID. Open domains get a vacuum margin of two nodes, so that the walls' tops and outer faces
# are lit and seen as in open space (light that leaves the domain never comes back, so more
# would change nothing). Below: vertical slices through the three balls' centres.

# %%
# accuracy=None: the solver's own defaults, with these settings on top (accuracy="draft",
# "default" or "high" picks a preset from notebook 03's study instead)
model = df.forward_model(scene, "sweep", accuracy=None, resolution=N, M=M, tol=TOL)
lat = model.lattice
print(lat)


def node(axis, x):
    """The lattice index of world coordinate x along axis 0, 1, 2."""
    return int(np.floor((x - lat.origin[axis]) / lat.h))


balls = [s for s in scene.shapes if s.kind == "sphere"]
plot.lattice_slices(lat, "node_type", axis="y", index=[node(1, b.center[1]) for b in balls])

# %%
# which shape each node belongs to, and the fog density multiplier (0 in solids and outside)
display(plot.lattice_slices(lat, "material", axis="y", index=node(1, balls[0].center[1]),
                            scene=scene))
plot.lattice_slices(lat, "density", axis="y", index=node(1, balls[0].center[1]))

# %% [markdown]
# Surface normals at SURFACE nodes (analytic here: the gradient of the nearest shape's signed
# distance), in a horizontal slice through the highest ball. Colour encodes the normal's
# direction, arrows its in-plane part.

# %%
plot.lattice_slices(lat, "normal", axis="z", index=node(2, balls[0].center[2]))

# %% [markdown]
# ## 3. Render with the sweep solver
#
# `df.render(model)` solves the light once (`model.light(params)`), renders every camera from it
# (`model.images_from(light, params)`) and times each stage (compilation reported apart).
# `model(params)` does the same in one jitted call, without the timings. The solver iterates until
# its estimated remaining error falls below `tol`: by default by GMRES with the six sweeps as its
# operator (`method="gmres"`), which needs far fewer sweeps than the paper's plain Jacobi iteration
# (`method="jacobi"`, one more bounce of light per iteration; notebook 04 uses it). Below, GMRES's
# relative residual after each application of the sweeps.

# %%
out = df.render(model)
t = out.timings
print(f"light {t['light_s']:.2f} s (+ {t['light_compile_s']:.1f} s compile), "
      f"images {t['images_s']:.2f} s (+ {t['images_compile_s']:.1f} s compile), "
      f"{int(out.light.iterations)} iterations, "
      f"estimated error {float(out.light.error_estimate):.1e}, {out.result.name}")
plot.image_grid(out.images, suptitle=f"fog-balls, sweep solver, N = {N}, M = {M}")

# %%
fig = plot.convergence(out.light, tol=TOL, label="fog-balls")
fig.axes[0].set_xlabel("GMRES iteration (one application of the six sweeps)")
fig.axes[0].set_ylabel("relative residual")
fig

# %% [markdown]
# ## 4. Light inside the fog
#
# The uncollided sun (the shadow buffer of the first-collision source) and the scattered
# fluence Λ, in a vertical slice through the highest ball: its shadow is a tube through the
# fog, slanted like the sun.

# %%
iy = node(1, balls[0].center[1])
display(plot.lattice_slices(lat, np.asarray(out.light.sun_fluence), axis="y", index=iy,
                            label="uncollided sun F·T (W m⁻²)"))
plot.lattice_slices(lat, np.asarray(out.light.fluence), axis="y", index=iy,
                    label="scattered fluence Λ (W m⁻²)")

# %% [markdown]
# ## 5. Against Mitsuba 3
#
# The references are unbiased Monte Carlo renders of the very same scene files (4096 samples
# per pixel), shipped with difffog (`difffog.study.references`: `reference(scene, camera)` is
# the image and its known per-pixel noise, which the error below removes in quadrature). Camera
# rays meet the exact shapes, so edges and shadows fall on the right pixels; at N = 64 fog-balls
# is within 1.4% (top) and 1.5% (oblique), and at the small size the coarse lattice's diffuse
# light adds a few per cent.

# %%
print("references:", references_dir() / "fog-balls")
for cam, img in out.images.items():
    ref, noise = reference("fog-balls", cam)
    display(plot.image_grid({f"difffog / {cam}": img, "Mitsuba 3": ref}))
    display(plot.error_map(img, ref, noise=noise, title=f"fog-balls / {cam}"))

# %% [markdown]
# ## 6. Sweep and splat side by side
#
# difffog's second forward model, the splat (`df.forward_model(scene, "splat")`, a `df.SplatModel`:
# Zhang & Crawfis' sheet-based splatting), renders the same scene in one pass over sheets
# perpendicular to the half-way vector between the eye and the sun, with no 3-D light volume and no
# iteration. It keeps single scattering of the sun, multiple forward and back scattering along the
# light, and shadows; it drops light that bounces off surfaces into the fog or onto other surfaces,
# and it treats the sky as an ambient term. Both models share the interface (`model.light(p)`,
# `model(p)`, `df.render`), the `Params`, the cameras and the tone map below. The splat's light and
# images come out of the same pass, so its time is all in the light.

# %%
splat_model = df.forward_model(scene, "splat", accuracy=None, resolution=N)
splat = df.render(splat_model)
ts = splat.timings
print(f"splat: {ts['light_s'] + ts['images_s']:.2f} s (+ "
      f"{ts['light_compile_s'] + ts['images_compile_s']:.1f} s compile), "
      f"against the sweep's {t['light_s'] + t['images_s']:.2f} s (+ "
      f"{t['light_compile_s'] + t['images_compile_s']:.1f} s compile)")
both = {f"sweep / {k}": v for k, v in out.images.items()}
both |= {f"splat / {k}": v for k, v in splat.images.items()}
plot.image_grid(both, ncols=len(out.images), suptitle=f"fog-balls at N = {N}: sweep (first row), "
                "splat (second row)")

# %%
for cam in out.images:
    display(plot.error_map(splat.images[cam], out.images[cam],
                           title=f"splat against sweep, {cam}"))

# %% [markdown]
# Against the Mitsuba 3 reference. In this walled box the light that bounces
# between the walls, the floor and the fog is a fifth of what the cameras see, and the splat
# has none of it: its images are 17–24% too dark. At N = 64 the splat is 25% / 29% off (top /
# oblique) against the sweep's 1.4% / 1.5% (`benchmarks/results/splat_references.md`,
# `benchmarks/results/references.md`). The splat's ground is the forward-scattering
# cloud of `cloud-plane` and polygon meshes, and time: notebooks 03 and 04.

# %%
print(f"{'camera':8s} {'sweep':>8s} {'splat':>8s}   (relative RMSE vs Mitsuba 3, "
      "reference noise removed; bias of the mean)")
for cam in out.images:
    ref, noise = reference("fog-balls", cam)
    e = {k: plot.image_errors(imgs[cam], ref, noise) for k, imgs in
         [("sweep", out.images), ("splat", splat.images)]}
    print(f"{cam:8s} {100 * e['sweep']['rel_rmse_corr']:7.1f}% "
          f"{100 * e['splat']['rel_rmse_corr']:7.1f}%   bias "
          f"{100 * e['sweep']['bias']:+.1f}% / {100 * e['splat']['bias']:+.1f}%")

# %% [markdown]
# ## 7. Sliders
#
# A draft model (24 nodes, M = 2, a loose tolerance, one ray per pixel) re-renders in well
# under a second once compiled, because moving a slider only changes `Params`: the lattice is
# not rebuilt and nothing is recompiled. The exposure stays fixed, so brighter means brighter.
# The sun's *direction* is geometry (it sets the shadow buffer's sweep), so changing it needs a
# new model, e.g. `df.forward_model(df.load_scene("fog-balls", ["sun.zenith_deg=40"]), "sweep")`.

# %%
import ipywidgets as widgets

draft = df.forward_model(scene, "sweep", accuracy=None, resolution=24, supersample=1, M=2,
                         tol=1e-2, max_iterations=60)
p0 = draft.params()
shape_names = [s.name for s in scene.shapes]


def draft_images(zeta, gamma, albedo, sun, sky):
    p = df.set_param(p0, scene, "fog.scattering", zeta)
    p = df.set_param(p, scene, "fog.absorption", gamma)
    for name in shape_names:
        p = df.set_param(p, scene, f"shape.{name}.albedo", albedo)
    p = df.set_param(p, scene, "sun.irradiance", sun)
    p = df.set_param(p, scene, "sky.radiance", sky)
    # throw=False: a slider at an extreme may need more than the draft's 60 iterations; show
    # what they give rather than raise
    return {k: np.asarray(v) for k, v in draft(p, throw=False).items()}


t0 = time.perf_counter()
first = draft_images(fog.scattering, fog.absorption, 0.8, sun.irradiance, scene.sky.radiance)
scale = plot.exposure(first)  # fixed from here on
print(f"draft model compiled and ran in {time.perf_counter() - t0:.1f} s")

# %%
slider = {"continuous_update": False, "style": {"description_width": "9em"},
          "layout": widgets.Layout(width="26em")}
sliders = {
    "zeta": widgets.FloatSlider(fog.scattering, min=0.0, max=10.0, step=0.1,
                                description="ζ scattering (1/unit)", **slider),
    "gamma": widgets.FloatSlider(fog.absorption, min=0.0, max=5.0, step=0.05,
                                 description="γ absorption (1/unit)", **slider),
    "albedo": widgets.FloatSlider(0.8, min=0.0, max=0.99, step=0.01,
                                  description="surface albedo ρ", **slider),
    "sun": widgets.FloatSlider(sun.irradiance, min=0.0, max=10.0, step=0.1,
                               description="sun (W m⁻²)", **slider),
    "sky": widgets.FloatSlider(scene.sky.radiance, min=0.0, max=1.0, step=0.01,
                               description="sky (W m⁻² sr⁻¹)", **slider),
}
status = widgets.Label()
view = widgets.Output()
last = {}


def update(change=None):
    t = time.perf_counter()
    last.update(draft_images(**{k: s.value for k, s in sliders.items()}))
    status.value = f"re-rendered in {time.perf_counter() - t:.2f} s (draft: N = 24, M = 2)"
    with view:
        view.clear_output(wait=True)
        display(plot.image_grid(last, scale=scale))


for s in sliders.values():
    s.observe(update, names="value")
update()
widgets.VBox([widgets.HBox([widgets.VBox(list(sliders.values())[:3]),
                            widgets.VBox(list(sliders.values())[3:] + [status])]), view])

# %% [markdown]
# Setting a slider from code does what dragging it does. Here ζ drops from 2 to 0.5 per unit:
# more sunlight reaches the floor, but the thinner fog scatters less of it towards the camera,
# and the fog's glow is most of what both cameras see, so both views get darker on average.
# Below, the images at ζ = 0.5 under the sliders' fixed exposure (the sliders themselves need a
# running kernel; a notebook read on the web shows this figure instead):

# %%
before = {k: float(v.mean()) for k, v in last.items()}
sliders["zeta"].value = 0.5
after = {k: float(v.mean()) for k, v in last.items()}
for k, b in before.items():
    print(f"{k:8s} mean radiance {b:.4f} -> {after[k]:.4f} W m⁻² sr⁻¹")
print(status.value)
assert before != after, "the slider did not re-render"
thin = dict(last)
sliders["zeta"].value = fog.scattering
plot.image_grid(thin, scale=scale, suptitle="ζ = 0.5 per unit (draft)")
