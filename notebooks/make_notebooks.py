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
(compilation reported apart). The solver iterates until its estimated remaining error falls
below `tol`: by default by GMRES with the six sweeps as its operator (`method="gmres"`), which
needs far fewer sweeps than the paper's plain Jacobi iteration (`method="jacobi"`, one more
bounce of light per iteration; notebook 04 uses it). Below, GMRES's relative residual after
each application of the sweeps."""),
    code("""\
out = renderer.render()
t = out.timings
print(f"solve {t['solve_s']:.2f} s (+ {t['solve_compile_s']:.1f} s compile), "
      f"render {t['render_s']:.2f} s (+ {t['render_compile_s']:.1f} s compile), "
      f"{int(out.light.iterations)} iterations, "
      f"estimated error {float(out.light.error_estimate):.1e}")
plot.image_grid(out.images, suptitle=f"fog-balls, sweep solver, N = {N}, M = {M}")"""),
    code("""\
fig = plot.convergence(out.light, tol=TOL, label="fog-balls")
fig.axes[0].set_xlabel("GMRES iteration (one application of the six sweeps)")
fig.axes[0].set_ylabel("relative residual")
fig"""),
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

    Both with the paper's method, plain Jacobi iteration (difffog's default is GMRES, whose
    iterations are not bounces of light).  One Renderer (one lattice, one compiled camera
    pass) serves both: a second SweepSolver with the same M solves on its prepared geometry.\"\"\"
    r = df.Renderer(scene, resolution=N, solver=df.SweepSolver(M=M, tol=TOL, max_iterations=500,
                                                               method="jacobi"))
    p = r.params()
    paper_solve = jax.jit(df.SweepSolver(M=M, max_iterations=iterations, tol=0.0,
                                         method="jacobi").solve)
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
kernels = {"no multiple scattering (Fig. 1)": {"forward_scatter": False, "back_scatter": False},
           "multiple forward (Fig. 2)": {"forward_scatter": True, "back_scatter": False},
           "forward + back (Fig. 4)": {"forward_scatter": True, "back_scatter": True}}
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
plt.close(fig)"""),
]

FITTING = [
    md("""\
# 02 — Fitting fog and albedo to images

`difffog.fit` adjusts the fog's scattering ζ, its absorption γ and a surface albedo ρ until
the rendered images match target images, by Levenberg–Marquardt on the differentiable sweep
solver. This notebook fits the `fog-balls` scene to the synthetic targets in
`data_synthetic/` (rendered with known parameters at N = 48, M = 4, finer than the fits), and
looks at what the fit says about itself: its convergence, its residual, its standard errors
and correlations, what 5% image noise changes, and what a second view adds.

The size switch: `small` (what the test suite runs: a 24-node lattice, M = 2, one sixty-fourth
of the pixels, a loose light tolerance; two to three minutes on 2 busy CPU cores, most of it
compiling) or `full` (the recovery study's settings: N = 24, M = 3, a sixteenth of the pixels;
four to five minutes). Three fits share one compiled step (section 2)."""),
    code(SIZE_SWITCH),
    code("""\
# the fit's own settings (the lattice is coarser than the targets' N = 48, M = 4 on purpose:
# a fit that uses the very model that made its targets finds them exactly, the "inverse crime")
FIT_N = 24  # lattice nodes along the domain
FIT_M = 2 if SMALL else 3  # direction half-width
DOWNSAMPLE = 8 if SMALL else 4  # fit each camera at 1/DOWNSAMPLE of its width and height
LIGHT_TOL = 1e-3 if SMALL else 1e-5  # the light solve's tolerance inside the fit
MAX_STEPS = 12 if SMALL else 30
print(f"fit: N = {FIT_N}, M = {FIT_M}, downsample {DOWNSAMPLE}, light tol {LIGHT_TOL:g}")"""),
    code("""\
import dataclasses
import json
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from IPython.display import display

import difffog as df
from difffog import plot"""),
    md("""\
## 1. The targets and the truth

`data_synthetic/truth.json` holds the parameters each target set was rendered with; set 0 of
`fog-balls` is the scene as shipped (ζ = 2, γ = 0.5 per unit length, walls' albedo 0.7). Each
camera comes noise-free, with 1% and with 5% Gaussian noise (σ = that fraction of the image
mean, per pixel). The fit starts far from the truth: ζ × 0.6, γ × 1.6, albedo − 0.15."""),
    code("""\
DATA = Path.cwd().parent / "data_synthetic"
scene = df.load_scene("fog-balls")
truth = json.loads((DATA / "truth.json").read_text())["fog-balls"]["sets"][0]["params"]
init = {"fog.scattering": 1.2, "fog.absorption": 0.8, "shape.walls.albedo": 0.55}
VIEWS = ["oblique", "top"]
targets = {noise: {v: np.load(DATA / "fog-balls" / "set0" / f"{v}_{noise}.npy") for v in VIEWS}
           for noise in ("noise01", "noise05")}
print("truth:", truth)
print("start:", init)
plot.image_grid({f"{v}, {n[-2:].lstrip('0')}% noise": targets[n][v]
                 for n in targets for v in VIEWS}, ncols=2,
                suptitle="fog-balls set 0: the targets (full resolution)")"""),
    md("""\
## 2. The forward model, and one view

`df.fit(scene, targets, unknowns, forward=..., downsample=k)` renders every camera at 1/k of
its size and box-averages the targets to match. Passing one forward model (a `Renderer` built
once) to several fits lets them share one compiled fit step. So does giving every fit the
same views: a view with weight zero everywhere takes no part in the fit (its pixels are left
out of the residual, the standard errors and the degrees of freedom), so "the top view only"
below is both views with the oblique one masked out."""),
    code("""\
small_cams = tuple(dataclasses.replace(c, resolution=(c.width // DOWNSAMPLE,
                                                      c.height // DOWNSAMPLE))
                   for c in scene.cameras)
forward = df.Renderer(scene.replace(cameras=small_cams), resolution=FIT_N, supersample=2,
                      solver=df.SweepSolver(M=FIT_M, tol=LIGHT_TOL, max_iterations=1000,
                                            adjoint_rtol=1e-4))
print(forward.lattice)
print("fit images:", {c.name: (c.height, c.width) for c in small_cams})


def fit(noise, views):
    \"\"\"Fit the unknowns to the targets with that noise, using only ``views``.\"\"\"
    weights = {v: np.full(targets[noise][v].shape, float(v in views)) for v in VIEWS}
    return df.fit(scene, targets[noise], init, forward=forward, downsample=DOWNSAMPLE,
                  weights=weights, max_steps=MAX_STEPS, progress=False)


top1 = fit("noise01", ["top"])
print(top1.summary(truth))"""),
    md("""\
## 3. Convergence

Each Levenberg–Marquardt step solves the light once for the residual and once more per
unknown for the Jacobian (forward mode, tangent light solves). The loss (half the sum of
squared residuals, each pixel's residual in units of the target's RMS) falls within two or
three steps to a floor that is the forward model's bias (section 6), then stays there: the fit
stops when optimistix' tolerances are met or the loss stops falling (`loss_stalled`). Step 1
evaluates the start; the first step's time includes compiling the fit."""),
    code("""\
def convergence_figure(res, title):
    steps = [h["step"] for h in res.history]
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(10, 3.4), layout="constrained")
    ax0.semilogy(steps, [h["loss"] for h in res.history], marker="o")
    ax0.set_xlabel("Levenberg–Marquardt step")
    ax0.set_ylabel("loss ½Σr² (r in units of the target RMS)")
    ax0.grid(True, which="both", alpha=0.3)
    for p in res.paths:
        ax1.plot([0] + steps, [100 * (v / truth[p] - 1) for v in
                               [res.initial[p]] + [h["values"][p] for h in res.history]],
                 marker="o", label=p)
    ax1.axhline(0.0, color="k", lw=0.8)
    ax1.set_xlabel("Levenberg–Marquardt step")
    ax1.set_ylabel("estimate − truth (% of the truth)")
    ax1.legend(fontsize=8)
    ax1.grid(True, alpha=0.3)
    fig.suptitle(title)
    plt.close(fig)
    return fig


print(f"{top1.result} after {top1.iterations} steps, {top1.time_s:.0f} s "
      f"(first step with compilation {top1.history[0]['time_s']:.0f} s)")
convergence_figure(top1, "fog-balls, top view, 1% noise")"""),
    md("""\
## 4. Target, fit and residual

The fitted image against its (box-averaged) target, under one tone map, and the signed
difference. What is left is not noise: it sits on the walls' top rims (a wall 0.05 thick is
about one node of the 24-node lattice and under a pixel of the reduced image, so how bright
its rim comes out depends on where the lattice nodes and the pixels' samples fall) and at the
balls' edges, where the coarse model cannot draw what the N = 48 one did. `weights=` (a mask
per view) can leave such pixels out of a fit."""),
    code("""\
display(plot.image_grid({"target (top, 1% noise)": top1.targets["top"],
                         "fitted": top1.images["top"]}))
plot.error_map(top1.images["top"], top1.targets["top"], relative=False,
               title="fitted − target, top view")"""),
    md("""\
## 5. Standard errors and correlations

The standard errors come from the Gauss–Newton covariance s²(JᵀJ)⁻¹ at the optimum, with s²
the residual variance. ζ and γ are strongly correlated in one view: both dim the light on its
way through the fog, and a view from above sees mostly their sum. The albedo of the walls is
nearly independent of them."""),
    code("""\
SHORT = {"fog.scattering": "ζ", "fog.absorption": "γ", "shape.walls.albedo": "ρ walls"}


def correlation_heatmap(res, title, ax):
    names = [SHORT.get(p, p) for p in res.paths]
    im = ax.imshow(res.correlation, cmap="RdBu_r", vmin=-1.0, vmax=1.0)
    ax.set_xticks(range(len(names)), names)
    ax.set_yticks(range(len(names)), names)
    ax.set_xlabel("unknown")
    ax.set_ylabel("unknown")
    for i in range(len(names)):
        for j in range(len(names)):
            ax.text(j, i, f"{res.correlation[i, j]:+.2f}", ha="center", va="center", fontsize=9,
                    color="w" if abs(res.correlation[i, j]) > 0.6 else "k")
    ax.set_title(title, fontsize=9)
    return im


fig, ax = plt.subplots(figsize=(4.4, 3.6), layout="constrained")
im = correlation_heatmap(top1, "correlation of the estimates, top view, 1% noise", ax)
fig.colorbar(im, ax=ax, label="correlation coefficient")
plt.close(fig)
fig"""),
    md("""\
## 6. The error is the model's, not the noise's

The estimates are off because the forward model (N = 24) does not render exactly what the
targets' N = 48, M = 4 model did: the fit finds the parameters with which the coarse model
best imitates the fine one. The check: render the fit's own model at the *true* parameters.
Its misfit to the target is the model's bias, and it is larger than the residual at the
fitted parameters, so the truth fits *worse* than the estimate. No fit can remove that; only
a finer forward model (larger N and M) can. The standard errors assume that the residual is
noise: here it is mostly bias, which sets their size but not their meaning, and the truth
may or may not lie within ±2 of them (the `error/se` column).

The recovery study (`benchmarks/results/recovery.md`, N = 24, M = 3, both views at 1/4
size, the full size of this notebook) measured it: at 1% noise ζ −5.9% (± 1.2%), γ −1.6%
(± 1.0%), the walls' albedo +4.8% (± 0.2%); with 5% noise −5.8%, −1.6%, +4.8% (the same);
against the Mitsuba 3 reference instead of synthetic targets −11%, −4.4%, +6.8%. The
model's misfit at the truth was 8.4% of the target mean. The truth lies outside ±2 standard
errors for ζ and the albedo in every case. At the small size (M = 2, 1/8 of the pixels)
the bias is larger still."""),
    code("""\
def misfit(res, views):
    \"\"\"RMS of (model − target) over the fitted views, % of the target mean: the forward model
    at the true parameters (its bias) and at the fitted ones (the fit's residual).\"\"\"
    p = forward.params()
    for path, v in truth.items():
        p = df.set_param(p, scene, path, v)
    at_truth = {k: np.asarray(v) for k, v in forward(p).items()}
    t = np.concatenate([res.targets[v].ravel() for v in views])
    out = {}
    for label, imgs in (("at the truth", at_truth), ("at the fit", res.images)):
        d = np.concatenate([(imgs[v] - res.targets[v]).ravel() for v in views])
        out[label] = 100 * float(np.sqrt(np.mean(d ** 2)) / t.mean())
    return out


def report(res, views, label):
    print(f"{label}: {res.result} after {res.iterations} steps, {res.time_s:.0f} s")
    print(f"  {'unknown':20s} {'truth':>7s} {'estimate':>9s} {'error %':>8s} {'± se %':>7s} "
          f"{'error/se':>9s}")
    for p in res.paths:
        err, se = res.estimates[p] / truth[p] - 1, res.stderr[p] / truth[p]
        print(f"  {p:20s} {truth[p]:7.3g} {res.estimates[p]:9.4g} {100 * err:+8.2f} "
              f"{100 * se:7.2f} {err / se:+9.1f}")
    m = misfit(res, views)
    print("  image RMS misfit, % of the target mean: "
          + ", ".join(f"{k} {v:.2f}%" for k, v in m.items()))
    return m


m1 = report(top1, ["top"], "top view, 1% noise")
assert m1["at the truth"] > m1["at the fit"]  # the model's bias: the truth fits worse"""),
    md("""\
## 7. Five per cent noise

The same fit to the targets with 5% noise. The noise is per full-resolution pixel, and the fit
box-averages DOWNSAMPLE × DOWNSAMPLE of them into one of its pixels, which divides the noise by
DOWNSAMPLE (to 0.6% of the mean at the small size, 1.25% at the full size): next to the model's
bias it hardly shows. The estimates move by a fraction of a per cent; the standard errors,
which take s² from the residual, stay what the bias makes them."""),
    code("""\
top5 = fit("noise05", ["top"])
m5 = report(top5, ["top"], "top view, 5% noise")
print("\\nestimate with 5% noise − with 1% noise, % of the truth:")
for p in top1.paths:
    print(f"  {p:20s} {100 * (top5.estimates[p] - top1.estimates[p]) / truth[p]:+.2f}")
display(plot.image_grid({"target (top, 5% noise)": top5.targets["top"],
                         "fitted": top5.images["top"]}))
plot.error_map(top5.images["top"], top5.targets["top"], relative=False,
               title="fitted − target, top view, 5% noise")"""),
    md("""\
## 8. One view against two

Adding the oblique view (both views, 1% noise) gives the fit light that has travelled through
the fog sideways as well as from above: more pixels, and pixels that depend on the unknowns
differently. The standard errors of ζ and γ shrink by a quarter to a third (the albedo's,
already small, does not); their correlation stays high (0.8–0.9 either way), because both
views see mostly the fog's extinction ζ + γ and its glow, and tell its scattering from its
absorption only through how bright the glow is for a given dimming. The
estimates' distance from the truth is again set by the model's bias, now in both views."""),
    code("""\
both1 = fit("noise01", ["oblique", "top"])
mb = report(both1, ["oblique", "top"], "both views, 1% noise")
print(f"\\n{'standard error, % of the truth':32s} {'top only':>9s} {'both':>9s}")
for p in top1.paths:
    print(f"  {p:30s} {100 * top1.stderr[p] / truth[p]:9.2f} "
          f"{100 * both1.stderr[p] / truth[p]:9.2f}")
print(f"  {'correlation of ζ and γ':30s} {top1.correlation[0, 1]:9.3f} "
      f"{both1.correlation[0, 1]:9.3f}")
fig, axes = plt.subplots(1, 2, figsize=(8.6, 3.6), layout="constrained")
correlation_heatmap(top1, "top view only", axes[0])
im = correlation_heatmap(both1, "top and oblique views", axes[1])
fig.colorbar(im, ax=axes, label="correlation coefficient")
plt.close(fig)
fig"""),
    code("""\
display(convergence_figure(both1, "fog-balls, both views, 1% noise"))
display(plot.image_grid({"target (oblique, 1% noise)": both1.targets["oblique"],
                         "fitted": both1.images["oblique"]}))
plot.error_map(both1.images["oblique"], both1.targets["oblique"], relative=False,
               title="fitted − target, oblique view")"""),
    md("""\
## What to take from this

* The fit converges in a handful of steps from a start 20–60% off, and reports standard errors
  and correlations with the estimates.
* At a coarse lattice its error against the truth is the forward model's bias, not the noise:
  the recovery study at N = 24 (`benchmarks/results/recovery.md`) found ζ 6% low, γ 1.6% low
  and the albedo 5% high whatever the noise (1% or 5%), and 11%, 4% and 7% off against the
  Mitsuba 3 image; the standard errors (0.2–1.2%) do not cover that. Read them as the noise's
  share of the uncertainty only, and check the bias as above: render at the estimates with a
  finer model (larger N and M), or fit at two resolutions and see how far the estimates move.
* A second view shrinks ζ's and γ's standard errors but leaves them strongly correlated: what
  separates them is the ratio of glow to dimming, which every view of this scene sees alike.
* `difffog fit` does the same from the command line and writes the estimates, the convergence
  plot and the residual images (README, "Fitting")."""),
]


SPEED = [
    md("""\
# 03 — Speed against accuracy

Every solver has knobs that trade time for accuracy, and difffog measures that trade instead
of guessing it: `difffog bench` renders the benchmark scenes at a ladder of settings of both
solvers, times them, and scores each image against the independent Mitsuba 3 references.
This notebook explains the knobs, plots the study (its committed results when they are in
`benchmarks/results/bench/`, otherwise, and always at the small size, a quick run of one
scene made here), sets it beside Mitsuba's own time-versus-error curve, and shows what the
accuracy presets (`--accuracy draft|default|high`) are."""),
    code(SIZE_SWITCH),
    code("""\
import csv
import math
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from IPython.display import Markdown, display

from difffog import plot
from difffog._bench import read_rows, run_bench
from difffog._presets import PRESETS"""),
    code(REFERENCES),
    md("""\
## 1. The knobs

| solver | knob | what it buys | what it costs |
|---|---|---|---|
| sweep | `resolution` N: lattice nodes along the longest side | smaller voxels h = L/N: sharper shadows and edges, thin walls that do not leak | time and memory ∝ N³ per iteration |
| sweep | `M`: direction half-width, (2M+1)² directions per cube face | finer angles: fewer ray effects, better grazing single scattering | time ∝ (2M+1)², compile time |
| sweep | `tol`: the estimated remaining error where the iteration (GMRES by default) stops | a converged light field; 1e-3 already changes images by < 0.1% | iterations, more at high albedo |
| splat | `resolution`: voxels splatted along the longest side | finer footprints and shadow buffer | time ∝ voxels, setup (host ray casting) |
| splat | `sheets`: slices per camera pass (default one per voxel) | little: the splat's light model, not the slicing, sets its error | time ∝ sheets |
| Mitsuba 3 | samples per pixel (spp) | noise ∝ 1/√spp, no bias | time ∝ spp |

Each row of the study records the warm time of one forward pass (the light solve and every
camera of the scene; `time_s`), the compile time paid once per process (`compile_s`), the
host set-up paid once per scene (`setup_s`), XLA's memory for the pass (`xla_mib`), the
sweep's iterations (applications of its six sweeps), and the relative RMSE against the reference with the reference's own
noise removed (`error`) and the bias of the mean (`bias`)."""),
    md("""\
## 2. The study

The committed study is `benchmarks/results/bench/bench.csv` (`difffog bench` over the four
benchmark scenes and both solvers: about an hour on 2 CPU cores). At the small size, or
when it is not there, `run_bench(..., quick=True)` runs one small setting per solver on
`cloud-plane` into a temporary folder (about a minute): the same rows, fewer of them."""),
    code("""\
BENCH_CSV = Path.cwd().parent / "benchmarks" / "results" / "bench" / "bench.csv"
# read_rows: bench.csv as a list of dicts, numbers as floats (NaN where a column does not apply)
committed = read_rows(BENCH_CSV) if BENCH_CSV.exists() else None
if committed is not None and not SMALL:
    rows, source = committed, f"the committed study ({BENCH_CSV.name})"
elif REFS.exists():
    with tempfile.TemporaryDirectory() as tmp:
        quick = run_bench(scenes=["cloud-plane"], solvers=["sweep", "splat"],
                          out=Path(tmp) / "bench", references=REFS, quick=True)
        rows = read_rows(quick.csv_path)
    source = "a quick run on cloud-plane (one setting per solver)"
else:
    raise RuntimeError("neither benchmarks/results/bench/bench.csv nor the references: "
                       "set DIFFFOG_REFERENCES to the folder of the Mitsuba 3 references")
ours = [r for r in rows if not r["solver"].startswith("mitsuba")]
mitsuba = [r for r in rows if r["solver"].startswith("mitsuba")]
scenes = sorted({r["scene"] for r in ours})
print(f"{source}: {len(ours)} difffog rows, {len(mitsuba)} Mitsuba rows; scenes {scenes}")
header = ("| solver | scene | setting | warm s | compile s | setup s | XLA MiB | iterations "
          "| error % | bias % |")
table = [header, "|---|---|---|---:|---:|---:|---:|---:|---:|---:|"]
for r in ours:
    table.append(f"| {r['solver']} | {r['scene']} | {r['setting']} | {r['time_s']:.2f} | "
                 f"{r['compile_s']:.1f} | {r['setup_s']:.1f} | {r['xla_mib']:.0f} | "
                 f"{r['iterations']:.0f} | {100 * r['error']:.1f} | {100 * r['bias']:+.1f} |")
display(Markdown("\\n".join(table)))"""),
    md("""\
## 3. Time against error: the Pareto plot

One panel per scene; warm time per image set (every camera of the scene, compile excluded)
against the error, both on log axes, one curve per solver, and the Pareto front: the
settings that no other setting beats in both time and error. Mitsuba's curve is its own
run on this machine at 4 … 1024 samples per pixel (the references' `convergence.csv`; it is
not re-run here)."""),
    code("""\
def pareto_panels(rows, title):
    scenes = sorted({r["scene"] for r in rows})
    fig, axes = plt.subplots(1, len(scenes), figsize=(4.6 * len(scenes), 3.8),
                             layout="constrained", squeeze=False)
    for ax, sc in zip(axes[0], scenes):
        rs = [dict(r, error=100 * r["error"]) for r in rows
              if r["scene"] == sc and np.isfinite(r["error"])]
        plot.pareto(rs, x="time_s", y="error", group="solver", annotate="setting", ax=ax,
                    xlabel="warm time per image set (s)",
                    ylabel="relative RMSE vs Mitsuba 3 reference (%)")
        ax.set_title(sc, fontsize=9)
    fig.suptitle(title)
    plt.close(fig)
    return fig


pareto_panels(rows, source)"""),
    md("""\
## 4. Mitsuba 3's curve, and what it takes to match difffog

A Monte Carlo renderer has no bias, only noise, and its error falls as 1/√spp: four times the
time for half the error. Below, the references' convergence run per camera against samples
per pixel, with a 1/√spp line through each curve's first point. Then, for each difffog row,
how long Mitsuba needs to reach the same error (interpolated on its curve, log-log), beside
difffog's warm time and its first render in a fresh process (set-up and compilation
included; Mitsuba's times are whole renders). The advantage is largest at coarse errors and
shrinks as the error asked for falls: difffog's error stops falling at its model bias (a few
to 30 per cent, depending on the scene and the view), Mitsuba's keeps falling as 1/√time."""),
    code("""\
conv = REFS / "convergence.csv"
if conv.exists():
    curves = {}
    with open(conv, newline="") as f:
        for r in csv.DictReader(f):
            if r["scene"] in scenes:
                curves.setdefault(f"{r['scene']} / {r['camera']}", []).append(
                    (float(r["spp"]), float(r["rel_rmse_corr"])))
    fig, ax = plt.subplots(figsize=(5.6, 3.8), layout="constrained")
    for label, pts in curves.items():
        spp, err = np.array(sorted(pts)).T
        line, = ax.loglog(spp, 100 * err, marker="o", ms=4, label=label)
        ax.loglog(spp, 100 * err[0] * np.sqrt(spp[0] / spp), ls=":", color=line.get_color())
    ax.set_xlabel("samples per pixel")
    ax.set_ylabel("relative RMSE vs reference (%)")
    ax.set_title("Mitsuba 3 (dotted: 1/√spp)", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    plt.close(fig)
    display(fig)"""),
    code("""\
def mitsuba_time_at(scene, error):
    \"\"\"Mitsuba's wall time (all cameras) to reach ``error`` on its curve, log-log
    interpolation; extrapolated with 1/√t beyond its last point.\"\"\"
    pts = sorted((r["time_s"], r["error"]) for r in mitsuba if r["scene"] == scene)
    if not pts:
        return math.nan
    t, e = np.log(np.array(pts)).T
    if np.log(error) < e[-1]:  # below its lowest error: error ∝ t^-1/2
        return float(np.exp(t[-1] + 2 * (e[-1] - np.log(error))))
    return float(np.exp(np.interp(-np.log(error), -e, t)))


labels, ours_t, first_t, theirs_t = [], [], [], []
print(f"{'solver':6s} {'scene':17s} {'setting':18s} {'error %':>8s} {'difffog s':>10s} "
      f"{'Mitsuba s':>10s} {'speed-up':>9s}")
for r in ours:
    tm = mitsuba_time_at(r["scene"], r["error"])
    labels.append(f"{r['solver']} {r['scene']}\\n{r['setting']}")
    ours_t.append(r["time_s"])
    first_t.append(r["time_s"] + r["compile_s"] + r["setup_s"])
    theirs_t.append(tm)
    print(f"{r['solver']:6s} {r['scene']:17s} {r['setting']:18s} {100 * r['error']:8.1f} "
          f"{r['time_s']:10.2f} {tm:10.1f} {tm / r['time_s']:8.0f}×")
fig, ax = plt.subplots(figsize=(min(16.0, max(5.0, 0.6 * len(labels))), 3.8),
                       layout="constrained")
x = np.arange(len(labels))
ax.bar(x - 0.27, ours_t, 0.27, label="difffog, warm")
ax.bar(x, first_t, 0.27, label="difffog, first render (set-up + compile)")
ax.bar(x + 0.27, theirs_t, 0.27, label="Mitsuba 3 to the same error")
ax.set_yscale("log")
ax.set_xticks(x, labels, fontsize=7, rotation=90 if len(labels) > 6 else 0)
ax.set_ylabel("time per image set (s)")
ax.set_title("time to reach each difffog row's error", fontsize=9)
ax.legend(fontsize=8)
plt.close(fig)
fig"""),
    md("""\
## 5. What a forward pass costs besides its warm time

In a notebook the first render of a new renderer pays the host set-up (voxelizing, and for
the splat ray casting its z-buffers and footprints) and XLA's compilation; after that only the
warm time counts, which is what a fit or a slider pays per evaluation. Memory is XLA's for one
forward pass (the sweep's grows with N³ and the directions, the splat's with the sheets'
area)."""),
    code("""\
labels = [f"{r['solver']} {r['scene']}\\n{r['setting']}" for r in ours]
x = np.arange(len(ours))
rot = 90 if len(ours) > 6 else 0
fig, ax = plt.subplots(figsize=(min(16.0, max(5.0, 0.5 * len(ours))), 3.8), layout="constrained")
bottom = np.zeros(len(ours))
for key, name in [("setup_s", "host set-up"), ("compile_s", "compile"),
                  ("time_s", "warm forward pass")]:
    v = np.array([r[key] for r in ours])
    ax.bar(x, v, bottom=bottom, label=name)
    bottom += v
ax.set_xticks(x, labels, fontsize=7, rotation=rot)
ax.set_ylabel("time (s)")
ax.set_title("first render = set-up + compile + warm", fontsize=9)
ax.legend(fontsize=8)
plt.close(fig)
display(fig)
fig, ax = plt.subplots(figsize=(min(16.0, max(5.0, 0.5 * len(ours))), 3.6), layout="constrained")
ax.bar(x, [r["xla_mib"] for r in ours], color="tab:purple")
ax.set_xticks(x, labels, fontsize=7, rotation=rot)
ax.set_ylabel("XLA memory per forward pass (MiB)")
ax.set_title("memory of one forward pass", fontsize=9)
plt.close(fig)
fig"""),
    md("""\
## 6. Where the splat wins and where it loses

From the rows above, per scene: each solver's most accurate setting and its fastest one.
The measured picture at N = 64 (`benchmarks/results/splat_references.md` and the README's
"Splat solver" section): the splat renders both cameras in 0.3–0.8 s against 5–14 s for the
sweep's solve, with no iteration. It comes within a few points of the sweep on `cloud-plane`
(13 / 37% against 11 / 31%, top / oblique) — the forward-scattering cloud under a polygon
airplane it was designed for — but is 2–3× the sweep's error in the translucent cube and
misses a fifth of the light in the walled `fog-balls` box (−19 to −24%), because light that
bounces between surfaces and the fog is outside its light model. More sheets do not help.
So: the splat for previews, for shadows' shapes, for clouds and for fits that need many
renders; the sweep when the answer has to be within a few per cent."""),
    code("""\
for sc in scenes:
    print(sc)
    for solver in ("sweep", "splat"):
        rs = [r for r in ours if r["scene"] == sc and r["solver"] == solver
              and np.isfinite(r["error"])]
        if not rs:
            print(f"  {solver}: not in this study")
            continue
        best = min(rs, key=lambda r: r["error"])
        fast = min(rs, key=lambda r: r["time_s"])
        print(f"  {solver}: most accurate {best['setting']} ({100 * best['error']:.1f}% in "
              f"{best['time_s']:.2f} s); fastest {fast['setting']} ({fast['time_s']:.2f} s, "
              f"{100 * fast['error']:.1f}%)")"""),
    code("""\
if committed is not None and SMALL:
    # at the small size the quick run is plotted above; the committed study is cheap to show
    display(pareto_panels(committed, f"the committed study ({BENCH_CSV.name})"))"""),
    md("""\
## 7. The accuracy presets

`--accuracy draft|default|high` on the command line, `accuracy=` in
`difffog._presets.forward_model`, pick a setting per solver from this study: the sweep's draft
is N = 32, M = 2 (seconds, about twice the default's error), its default N = 64, M = 3, its
high N = 96, M = 4; the splat's presets vary the resolution only, since more sheets do not
lower its error."""),
    code("""\
lines = ["| solver | preset | settings |", "|---|---|---|"]
for solver, levels in PRESETS.items():
    for level, s in levels.items():
        lines.append(f"| {solver} | {level} | "
                     + ", ".join(f"{k} = {'one per voxel' if v is None else v}"
                                 for k, v in s.items()) + " |")
display(Markdown("\\n".join(lines)))"""),
    md("""\
## 8. Re-running the study

```bash
difffog bench                                  # both solvers, the four benchmark scenes
difffog bench --scenes cloud-plane --solvers splat --out bench-cloud
difffog bench --quick --scenes fog-balls       # one small setting per solver (a smoke test)
difffog bench --references /path/to/references # default: ../shared/references
```

Each writes `bench.csv` (the rows above), `pareto.png` and `bench.md` into `--out` (default
`bench/`; written to a temporary folder and renamed, so a killed run leaves nothing
half-written). Times depend on the machine and on what else runs on it: compare settings
measured in the same run, and record the load (`uptime`) beside any figure you quote."""),
]


NOTEBOOKS = {
    "01-forward-rendering.ipynb": FORWARD,
    "02-fitting.ipynb": FITTING,
    "03-speed-vs-accuracy.ipynb": SPEED,
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
