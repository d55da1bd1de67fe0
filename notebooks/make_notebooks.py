"""Write the notebooks in this folder from the cell sources below.

    python notebooks/make_notebooks.py            # (re)write the .ipynb files
    python notebooks/make_notebooks.py --check    # exit 1 if a committed notebook is stale


The ``.ipynb`` files are generated, committed without outputs, and executed by
``tests/test_notebooks.py`` at the small size; edit the cells here, not in Jupyter, and
regenerate (the test checks that the committed files match this script).  Cell ids are
fixed so that regenerating an unchanged notebook changes nothing.

Size switch: ``DIFFFOG_NOTEBOOK_SIZE=small`` (what CI runs: lattices of 24 nodes, draft
solver tolerances) or ``full`` (the default, for people: 64 nodes, converged light).
"""

from __future__ import annotations

import sys
from pathlib import Path

import nbformat
from nbformat.v4 import new_code_cell, new_markdown_cell, new_notebook

HERE = Path(__file__).resolve().parent

SIZE_SWITCH = '''\
import os

# "small": what the test suite runs (a minute or two on 2 CPU cores);
# "full": the default, for people (a few minutes on 2 CPU cores)
SIZE = os.environ.get("DIFFFOG_NOTEBOOK_SIZE", "full")
if SIZE not in ("small", "full"):
    raise ValueError(f"DIFFFOG_NOTEBOOK_SIZE must be 'small' or 'full', got {SIZE!r}")
SMALL = SIZE == "small"
N = 24 if SMALL else 64  # lattice nodes along the longest side of the domain
M = 2 if SMALL else 3  # direction half-width: (2M+1)^2 directions per cube face
TOL = 1e-2 if SMALL else 1e-4  # the solver's estimated remaining relative error
print(f"size {SIZE}: N = {N}, M = {M}, tol = {TOL:g}")'''

REFERENCES = '''\
# The Mitsuba 3 references live next to the repository (../shared/references) when the
# project's shared folder is there; DIFFFOG_REFERENCES points elsewhere.
REFS = Path(os.environ.get("DIFFFOG_REFERENCES",
                           Path.cwd().parent.parent / "shared" / "references"))
print("references:", REFS if REFS.exists() else "not found (the comparison cells skip)")'''


def md(text: str):
    return ("markdown", text)


def code(text: str):
    return ("code", text)


FORWARD = [
    md("""\
# 01 — Forward rendering

Load one of the shared scenes, look at the lattice the solver runs on, render it with the
sweep solver (Langer, Breton & Zucker), compare the images with the independent Mitsuba 3
references, and move sliders for the fog and the light.

Everything runs on a CPU. The size switch below picks the lattice: `small` (24 nodes, what
the test suite runs) or `full` (64 nodes, the default). Set `DIFFFOG_NOTEBOOK_SIZE=small`
before starting Jupyter for a quick pass."""),
    code(SIZE_SWITCH),
    code("""\
import time
from pathlib import Path

import numpy as np
from IPython.display import display

import difffog as df
from difffog import plot"""),
    md("""\
## 1. The scene

`fog-balls`: three balls floating in a box of homogeneous fog with an open roof, lit by an
oblique sun and a dim sky (after Langer et al., Fig. 5). Lengths are in scene units; the fog's
scattering ζ and absorption γ are per unit length. `df.param_paths` lists what a fit (or a
slider) can change without rebuilding anything."""),
    code("""\
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
print("parameters:", ", ".join(df.param_paths(scene)))"""),
    md("""\
## 2. The lattice

A `Renderer` voxelizes the scene once (on the host, NumPy): each node is FREE (light travels
and scatters there), SURFACE (a shell M nodes thick around the solids, where light is
reflected) or SOLID. Open domains get a vacuum margin of M + 1 nodes so that light from the
sky reaches the walls' tops. Below: vertical slices through the three balls' centres."""),
    code("""\
renderer = df.Renderer(scene, resolution=N, solver=df.SweepSolver(M=M, tol=TOL))
lat = renderer.lattice
print(lat)


def node(axis, x):
    \"\"\"The lattice index of world coordinate x along axis 0, 1, 2.\"\"\"
    return int(np.floor((x - lat.origin[axis]) / lat.h))


balls = [s for s in scene.shapes if s.kind == "sphere"]
plot.lattice_slices(lat, "node_type", axis="y", index=[node(1, b.center[1]) for b in balls])"""),
    code("""\
# which shape each node belongs to, and the fog density multiplier (0 in solids and outside)
display(plot.lattice_slices(lat, "material", axis="y", index=node(1, balls[0].center[1]),
                            scene=scene))
plot.lattice_slices(lat, "density", axis="y", index=node(1, balls[0].center[1]))"""),
    md("""\
Surface normals at SURFACE nodes (analytic here: the gradient of the nearest shape's signed
distance), in a horizontal slice through the highest ball. Colour encodes the normal's
direction, arrows its in-plane part."""),
    code("""\
plot.lattice_slices(lat, "normal", axis="z", index=node(2, balls[0].center[2]))"""),
    md("""\
## 3. Render with the sweep solver

`renderer.render()` solves the light once for every camera and times each stage
(compilation reported apart). The Jacobi iteration stops when its estimated remaining error
falls below `tol`."""),
    code("""\
out = renderer.render()
t = out.timings
print(f"solve {t['solve_s']:.2f} s (+ {t['solve_compile_s']:.1f} s compile), "
      f"render {t['render_s']:.2f} s (+ {t['render_compile_s']:.1f} s compile), "
      f"{int(out.light.iterations)} iterations, "
      f"estimated error {float(out.light.error_estimate):.1e}")
plot.image_grid(out.images, suptitle=f"fog-balls, sweep solver, N = {N}, M = {M}")"""),
    code("""\
plot.convergence(out.light, tol=TOL, label="fog-balls")"""),
    md("""\
## 4. Light inside the fog

The uncollided sun (the shadow buffer of the first-collision source) and the scattered
fluence Λ, in a vertical slice through the highest ball: its shadow is a tube through the
fog, slanted like the sun."""),
    code("""\
iy = node(1, balls[0].center[1])
display(plot.lattice_slices(lat, np.asarray(out.light.sun_fluence), axis="y", index=iy,
                            label="uncollided sun F·T (W m⁻²)"))
plot.lattice_slices(lat, np.asarray(out.light.fluence), axis="y", index=iy,
                    label="scattered fluence Λ (W m⁻²)")"""),
    md("""\
## 5. Against Mitsuba 3

The references are unbiased Monte Carlo renders of the very same scene files (4096 samples
per pixel), with a known per-pixel noise that the error below removes in quadrature. At the
small size expect 10–30% relative RMSE, mostly at edges (the wall's top rim, shadow edges);
at N = 64 fog-balls is within 3.5% (top) and 18% (oblique, the rim lands a pixel off)."""),
    code(REFERENCES),
    code("""\
import json

if REFS.exists():
    for cam, img in out.images.items():
        ref = np.load(REFS / "fog-balls" / f"{cam}.npy")
        noise = json.loads((REFS / "fog-balls" / f"{cam}_stats.json").read_text())["ref_noise_rmse"]
        display(plot.image_grid({f"difffog / {cam}": img, "Mitsuba 3": ref}))
        display(plot.error_map(img, ref, noise=noise, title=f"fog-balls / {cam}"))"""),
    md("""\
## 6. Sweep and splat side by side

difffog's second solver, `SplatRenderer` (Zhang & Crawfis' sheet-based splatting), renders
the same scene in one pass over sheets perpendicular to the half-way vector between the eye
and the sun, with no 3-D light volume and no iteration. It keeps single scattering of the
sun, multiple forward and back scattering along the light, and shadows; it drops light that
bounces off surfaces into the fog or onto other surfaces, and it treats the sky as an
ambient term. Both solvers share the `Params`, the cameras and the tone map below."""),
    code("""\
splat_r = df.SplatRenderer(scene, resolution=N)
splat = splat_r.render()
ts = splat.timings
print(f"splat: render {ts['render_s']:.2f} s (+ {ts['render_compile_s']:.1f} s compile), "
      f"against the sweep's {t['solve_s'] + t['render_s']:.2f} s (+ "
      f"{t['solve_compile_s'] + t['render_compile_s']:.1f} s compile)")
both = {f"sweep / {k}": v for k, v in out.images.items()}
both |= {f"splat / {k}": v for k, v in splat.images.items()}
plot.image_grid(both, ncols=len(out.images), suptitle=f"fog-balls at N = {N}: sweep (first row), "
                "splat (second row)")"""),
    code("""\
for cam in out.images:
    display(plot.error_map(splat.images[cam], out.images[cam],
                           title=f"splat against sweep, {cam}"))"""),
    md("""\
Against the Mitsuba 3 reference (when present). In this walled box the light that bounces
between the walls, the floor and the fog is a fifth of what the cameras see, and the splat
has none of it: its images are 17–24% too dark. At N = 64 the splat is 25% / 29% off (top /
oblique) against the sweep's 3.5% / 18% (`benchmarks/results/splat_references.md`); at the
small size the coarse sweep's own error on the wall's rim can put the splat ahead in the
oblique view, not because the splat got better. The splat's ground is the forward-scattering
cloud of `cloud-plane` and polygon meshes, and time: notebooks 03 and 04."""),
    code("""\
if REFS.exists():
    print(f"{'camera':8s} {'sweep':>8s} {'splat':>8s}   (relative RMSE vs Mitsuba 3, "
          "reference noise removed; bias of the mean)")
    for cam in out.images:
        ref = np.load(REFS / "fog-balls" / f"{cam}.npy")
        noise = json.loads((REFS / "fog-balls" / f"{cam}_stats.json").read_text())["ref_noise_rmse"]
        e = {k: plot.image_errors(imgs[cam], ref, noise) for k, imgs in
             [("sweep", out.images), ("splat", splat.images)]}
        print(f"{cam:8s} {100 * e['sweep']['rel_rmse_corr']:7.1f}% "
              f"{100 * e['splat']['rel_rmse_corr']:7.1f}%   bias "
              f"{100 * e['sweep']['bias']:+.1f}% / {100 * e['splat']['bias']:+.1f}%")"""),
    md("""\
## 7. Sliders

A draft renderer (24 nodes, M = 2, a loose tolerance, one ray per pixel) re-renders in well
under a second once compiled, because moving a slider only changes `Params`: the lattice is
not rebuilt and nothing is recompiled. The exposure stays fixed, so brighter means brighter.
The sun's *direction* is geometry (it sets the shadow buffer's sweep), so changing it needs a
new `Renderer`, e.g. `df.Renderer(df.load_scene("fog-balls", ["sun.zenith_deg=40"]), ...)`."""),
    code("""\
import ipywidgets as widgets

draft = df.Renderer(scene, resolution=24, supersample=1,
                    solver=df.SweepSolver(M=2, tol=1e-2, max_iterations=60))
p0 = draft.params()
shape_names = [s.name for s in scene.shapes]


def draft_images(zeta, gamma, albedo, sun, sky):
    p = df.set_param(p0, scene, "fog.scattering", zeta)
    p = df.set_param(p, scene, "fog.absorption", gamma)
    for name in shape_names:
        p = df.set_param(p, scene, f"shape.{name}.albedo", albedo)
    p = df.set_param(p, scene, "sun.irradiance", sun)
    p = df.set_param(p, scene, "sky.radiance", sky)
    return {k: np.asarray(v) for k, v in draft(p).items()}


t0 = time.perf_counter()
first = draft_images(fog.scattering, fog.absorption, 0.8, sun.irradiance, scene.sky.radiance)
scale = plot.exposure(first)  # fixed from here on
print(f"draft renderer compiled and ran in {time.perf_counter() - t0:.1f} s")"""),
    code("""\
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
                            widgets.VBox(list(sliders.values())[3:] + [status])]), view])"""),
    md("""\
Setting a slider from code does what dragging it does. Here ζ drops from 2 to 0.5 per unit:
more sunlight reaches the floor, but the thinner fog scatters less of it towards the camera,
and the fog's glow is most of what both cameras see, so both views get darker on average:"""),
    code("""\
before = {k: float(v.mean()) for k, v in last.items()}
sliders["zeta"].value = 0.5
after = {k: float(v.mean()) for k, v in last.items()}
for k, b in before.items():
    print(f"{k:8s} mean radiance {b:.4f} -> {after[k]:.4f} W m⁻² sr⁻¹")
print(status.value)
assert before != after, "the slider did not re-render"
sliders["zeta"].value = fog.scattering"""),
]


PAPERS = [
    md("""\
# 04 — The papers' figures

The two papers behind difffog (`../shared/papers/`) show their methods on a handful of
scenes. This notebook re-makes those figures with difffog, with the papers' settings where
they state them (iterations) and the converged answer beside them, so that the difference
is visible.

* Langer, Breton & Zucker, *Massively Parallel Radiosity in the Presence of Multiple Isotropic
  Volume Scattering*: Fig. 4 (a ring in an open box, through the roof from four directions)
  and Fig. 5 (three balls in fog with their shadow tubes) — the sweep solver.
* Zhang & Crawfis, *Shadows and Soft Shadows with Participating Media Using Splatting*:
  Figs. 1, 2, 4 (clouds with no / forward / forward and back multiple scattering) and
  Figs. 8, 16 (hard and soft shadows of polygons on volumes) — the splat solver
  (`df.SplatRenderer`)."""),
    code(SIZE_SWITCH),
    code("""\
import dataclasses
import math
import time

import jax
import numpy as np
from IPython.display import display

import difffog as df
from difffog import plot

RES = 64 if SMALL else 128  # camera pixels (the cost is in the light solve, not here)"""),
    md("""\
## Langer et al., Fig. 4: a ring floating in a box, through the roof

*"A ring floating in a box is viewed through the top via parallel projection from four
different directions. No volume scattering was present. The albedo of all surfaces was 0.9.
The light source had two components, ambient and directed, both of which entered the box
through the open roof. The ambient component was a uniform hemispheric sky, and the directed
component was oblique, from the left. Twelve iterations were used."*

The shared `ring-box` scene is that set-up (sky 1 W m⁻² sr⁻¹, sun 2 W m⁻² at zenith 35°
from −x). Four orthographic cameras replace its own: tilted 20° from the vertical, from the four
sides, all aimed at the middle of the open roof, so each sees the ring through it (and the
outside of the nearest wall below the roof's edge)."""),
    code("""\
ring_scene = df.load_scene("ring-box")
roof = np.array([0.5, 0.5, 1.0])  # the middle of the open roof


def roof_camera(name, azimuth_deg, tilt_deg=20.0):
    \"\"\"An orthographic camera above the roof, tilted from the vertical towards azimuth.\"\"\"
    a, t = math.radians(azimuth_deg), math.radians(tilt_deg)
    toward = np.array([math.sin(t) * math.cos(a), math.sin(t) * math.sin(a), math.cos(t)])
    return df.Camera(name=name, kind="orthographic", position=tuple(roof + 0.5 * toward),
                     look_at=tuple(roof), up=(0.0, 0.0, 1.0), extent=(1.2, 1.2),
                     resolution=(RES, RES))


views = [roof_camera(f"from {side}", az) for side, az in
         [("+x", 0.0), ("+y", 90.0), ("-x", 180.0), ("-y", 270.0)]]
ring_scene = dataclasses.replace(ring_scene, cameras=tuple(views))


def paper_and_converged(scene, iterations):
    \"\"\"Light and images after the paper's number of Jacobi iterations and converged.

    One Renderer (one lattice, one compiled camera pass) serves both: a second SweepSolver
    with the same M solves on its prepared geometry.\"\"\"
    r = df.Renderer(scene, resolution=N, solver=df.SweepSolver(M=M, tol=TOL, max_iterations=500))
    p = r.params()
    paper_solve = jax.jit(df.SweepSolver(M=M, max_iterations=iterations, tol=0.0).solve)
    out = {}
    for key, solve in [("paper", lambda p: paper_solve(r.geometry, p)), ("converged", r.solve)]:
        t = time.perf_counter()
        light = solve(p)
        images = {k: np.asarray(v) for k, v in r.images(light, p).items()}
        out[key] = (light, images)
        print(f"{scene.title}, {key}: {int(light.iterations)} iterations, "
              f"{time.perf_counter() - t:.1f} s (compilation included)")
    return r, out


ring_r, ring = paper_and_converged(ring_scene, 12)  # the paper used twelve iterations
plot.image_grid(ring["paper"][1], ncols=4,
                suptitle=f"Langer et al. Fig. 4 with difffog: 12 iterations, N = {N}, M = {M}")"""),
    md("""\
How far are twelve iterations from the converged light? With albedo 0.9 everywhere each
bounce keeps most of the light, so the Jacobi iteration contracts slowly (about 0.8 per
iteration at N = 64: the slope below) and twelve iterations leave the inside of the box a few
per cent too dark, most of all on the floor and low on the walls, where light arrives after
several bounces. The paper's images were not converged either."""),
    code("""\
light, images = ring["converged"]
display(plot.image_grid(images, ncols=4, suptitle="converged"))
fig = plot.convergence(light, tol=TOL, label="ring-box, converged run")
fig.axes[0].axvline(12, color="grey", ls="--", lw=1, label="the paper's 12 iterations")
fig.axes[0].legend(fontsize=8)
display(fig)
name = views[2].name
plot.error_map(ring["paper"][1][name], images[name],
               title=f"12 iterations against converged, view {name}")"""),
    md("""\
## Langer et al., Fig. 5: three balls in fog and their shadow tubes

*"Three balls are shown floating in a box that is filled with homogeneous fog. The scene is
illuminated by a directed light source that is from above but slightly oblique. The shadows
cast by the balls are visible both in space (as tubes) and on the surface. Observe that the
deepest ball is the darkest since light is absorbed as it passes through the fog. Five
iterations of Coordinate Evolution were used."*

The shared `fog-balls` scene (ζ = 2, γ = 0.5 per unit, sun at zenith 20°), rendered after the
paper's five iterations and converged."""),
    code("""\
balls_scene = df.load_scene("fog-balls")
balls_r, balls = paper_and_converged(balls_scene, 5)  # the paper used five iterations
display(plot.image_grid({f"5 iterations / {k}": v for k, v in balls["paper"][1].items()}
                        | {f"converged / {k}": v for k, v in balls["converged"][1].items()},
                        ncols=2))
# fog of albedo 0.8 converges faster than the ring's box: five iterations are closer
plot.error_map(balls["paper"][1]["oblique"], balls["converged"][1]["oblique"],
               title="5 iterations against converged, oblique view")"""),
    md("""\
The tubes: the uncollided sunlight in vertical slices through each ball's centre. Each ball
casts a shadow tube slanted along the sun; the lower balls sit in the upper ones' fog, and
the floor carries all three shadows."""),
    code("""\
lat = balls_r.lattice
spheres = [(i, s) for i, s in enumerate(balls_scene.shapes) if s.kind == "sphere"]
iy = [int(np.floor((s.center[1] - lat.origin[1]) / lat.h)) for _, s in spheres]
plot.lattice_slices(lat, np.asarray(balls["converged"][0].sun_fluence), axis="y", index=iy,
                    label="uncollided sun F·T (W m⁻²)", ncols=3)"""),
    md("""\
*"The deepest ball is the darkest"*: the mean radiosity B (the Lambertian exitant radiance)
over each ball's surface nodes."""),
    code("""\
B = np.asarray(balls["converged"][0].radiosity)
shell = lat.node_type == 1  # SURFACE
for i, s in sorted(spheres, key=lambda x: -x[1].center[2]):
    mine = shell & (lat.material == i)
    print(f"{s.name:10s} centre height {s.center[2]:.2f}: mean radiosity "
          f"{B[mine].mean():.3f} W m⁻² sr⁻¹ over {mine.sum()} surface nodes")"""),
    md("""\
## Zhang & Crawfis, Figs. 1, 2, 4: a cloud with no, forward, and forward + back scattering

Their Figs. 1, 2 and 4 show the same clouds with no multiple scattering (attenuation and
single scattering only), with multiple forward scattering, and with forward and back
scattering. The shared `cloud-plane` scene's cloud (ζ = 60, γ = 0.6 per unit, a strongly
forward-scattering phase, g = 0.85) without its airplane and ground, seen from the side,
lit by a sun 60° from the zenith, once from behind the cloud and once from behind the viewer.
`similarity=False` keeps the paper's kernels (the Henyey–Greenstein phase of g = 0.85 for
the scattered light; the default `similarity=True` is the more accurate δ-scaled variant).
`forward_scatter` and `back_scatter` switch the paper's two multiple scattering terms."""),
    code("""\
SPLAT_N = 16 if SMALL else 48  # the splatted voxels along the longest side
PX = 64 if SMALL else 160  # camera width in pixels
side = df.Camera(name="side", kind="perspective", position=(0.5, -0.9, 0.45),
                 look_at=(0.5, 0.5, 0.45), up=(0.0, 0.0, 1.0), fov_deg=45.0,
                 resolution=(PX, PX * 3 // 4))
kernels = {"no multiple scattering (Fig. 1)": dict(forward_scatter=False, back_scatter=False),
           "multiple forward (Fig. 2)": dict(forward_scatter=True, back_scatter=False),
           "forward + back (Fig. 4)": dict(forward_scatter=True, back_scatter=True)}
lights = {"sun behind the cloud": 90.0, "sun behind the viewer": -90.0}  # sun azimuth (deg)
clouds, ratio = {}, {}
for light, azimuth in lights.items():
    sc = df.load_scene("cloud-plane", ["sun.zenith_deg=60", f"sun.azimuth_deg={azimuth}"])
    sc = sc.replace(shapes=(), cameras=(side,))  # the cloud alone
    imgs = {}
    for title, kw in kernels.items():
        r = df.SplatRenderer(sc, resolution=SPLAT_N, similarity=False, **kw)
        imgs[title] = np.asarray(r()["side"])
    # which pixels see the cloud: those that change when the fog is removed
    p0 = df.set_param(df.set_param(r.params(), sc, "fog.scattering", 0.0),
                      sc, "fog.absorption", 0.0)
    clear = np.asarray(r(p0)["side"])
    none = imgs["no multiple scattering (Fig. 1)"]
    mask = np.abs(none - clear) > 0.02 * float(clear.max())
    clouds[light] = imgs
    ratio[light] = {k: float(v[mask].mean() / none[mask].mean()) for k, v in imgs.items()}
    display(plot.image_grid(imgs, ncols=3, suptitle=f"cloud-plane's cloud, {light} "
                            f"(splat, N = {SPLAT_N}, the paper's kernels)"))"""),
    md("""\
How much brighter the cloud's pixels get when each multiple scattering term is switched on,
relative to single scattering alone. Lit from behind, forward scattering carries the light
on towards the viewer, so the cloud brightens most (the paper's Fig. 2 against Fig. 1); lit
from behind the viewer, light has to turn round to come back, which forward scattering
cannot do, and back scattering adds a little (Fig. 4)."""),
    code("""\
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
ax.set_xticks(np.arange(3), [k.replace(" (", "\\n(") for k in kernels], fontsize=8)
ax.axhline(1.0, color="k", lw=0.8)
ax.set_ylabel("mean cloud radiance / single scattering's")
ax.set_title(f"cloud brightness by scattering term (splat, N = {SPLAT_N})", fontsize=9)
ax.legend(fontsize=8)
display(fig)
plt.close(fig)
# the paper's point: multiple forward scattering brightens a back-lit cloud
assert ratio["sun behind the cloud"]["multiple forward (Fig. 2)"] > 1.05"""),
    md("""\
## Zhang & Crawfis, Figs. 8, 11, 16: hard and soft shadows

A point sun casts hard shadows; a sun of finite angular radius a penumbra that widens with
the distance between the occluder and what it shades. difffog's scenes give the sun an
`angular_radius_deg` (0 by default: a point). Here the same scenes with the sun's radius set
to 4° through the `--set`-style override, `df.apply_overrides(scene,
["sun.angular_radius_deg=4"])` — on the command line:
`difffog render cloud-plane --solver splat --set sun.angular_radius_deg=4 --out out`.
The airplane shades the cloud and the ground (its wings are 0.8 above the ground); the ring
inside the translucent cube sits 0.35 above it, so its penumbra is narrower."""),
    code("""\
shadow_cases = [("cloud-plane", "the airplane on the cloud and the ground"),
                ("translucent-cube", "the ring in the cube")]
pairs = {}
for name, what in shadow_cases:
    base = df.load_scene(name)
    cam = dataclasses.replace(base.camera("oblique"), resolution=(PX, PX * 3 // 4))
    base = base.replace(cameras=(cam,))
    pair = {}
    for radius in (0.0, 4.0):
        sc = df.apply_overrides(base, [f"sun.angular_radius_deg={radius}"])
        r = df.SplatRenderer(sc, resolution=SPLAT_N, soft_shadows=radius > 0)
        pair[f"sun radius {radius:g}°"] = np.asarray(r()["oblique"])
    pairs[name] = pair
    display(plot.image_grid(pair, ncols=2, suptitle=f"{name}: {what}, hard and soft shadows"))"""),
    md("""\
A profile across each shadow, along the image row where the hard and the soft shadows differ
most: the soft shadow's edge is spread over more pixels, and its core is less dark."""),
    code("""\
fig, axes = plt.subplots(1, 2, figsize=(10, 3.3), layout="constrained")
for ax, (name, pair) in zip(axes, pairs.items()):
    hard, soft = pair.values()
    row = int(np.argmax(np.abs(hard - soft).sum(axis=1)))
    for (label, img), style in zip(pair.items(), [dict(color="k"), dict(color="tab:orange")]):
        ax.plot(img[row], lw=1.2, label=label, **style)
    ax.set_xlabel("image column (pixel)")
    ax.set_ylabel(f"radiance ({plot.RADIANCE_UNIT})")
    ax.set_title(f"{name}: row {row} of the oblique view", fontsize=9)
    ax.legend(fontsize=8)
    print(f"{name}: the two differ by up to {np.abs(hard - soft).max():.3f} "
          f"{plot.RADIANCE_UNIT} (row {row}); mean radiance {hard.mean():.4f} hard, "
          f"{soft.mean():.4f} soft")
display(fig)
plt.close(fig)"""),
]

NOTEBOOKS = {
    "01-forward-rendering.ipynb": FORWARD,
    "04-the-papers.ipynb": PAPERS,
}


def build(cells, stem: str) -> nbformat.NotebookNode:
    nb = new_notebook()
    nb.metadata["kernelspec"] = {"display_name": "Python 3", "language": "python",
                                 "name": "python3"}
    nb.metadata["language_info"] = {"name": "python"}
    for i, (kind, text) in enumerate(cells):
        cell = new_markdown_cell(text) if kind == "markdown" else new_code_cell(text)
        cell["id"] = f"{stem[:2]}-{i:02d}"
        nb.cells.append(cell)
    nbformat.validate(nb)
    return nb


def render_all() -> dict[str, str]:
    """{file name: notebook JSON text} of every notebook."""
    return {name: nbformat.writes(build(cells, name), version=4) + "\n"
            for name, cells in NOTEBOOKS.items()}


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    check = "--check" in argv
    stale = []
    for name, text in render_all().items():
        path = HERE / name
        if check:
            if not path.exists() or path.read_text() != text:
                stale.append(name)
        else:
            path.write_text(text)
            print(f"wrote {path}")
    if stale:
        print(f"out of date (run python notebooks/make_notebooks.py): {', '.join(stale)}")
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
