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

difffog's second solver, the splat solver (Zhang & Crawfis' sheet-based splatting), is being
written and is **not in this version**. The cell below renders with it only when
`difffog.SplatRenderer` exists, and says so otherwise; it will show both solvers' images
under one tone map and their difference."""),
    code("""\
if hasattr(df, "SplatRenderer"):
    splat = df.SplatRenderer(scene, resolution=N).render()
    both = {f"sweep / {k}": v for k, v in out.images.items()}
    both |= {f"splat / {k}": v for k, v in splat.images.items()}
    display(plot.image_grid(both, ncols=len(out.images)))
    for cam in out.images:
        display(plot.error_map(splat.images[cam], out.images[cam], title=f"splat vs sweep, {cam}"))
else:
    print("difffog.SplatRenderer is not in this version: only the sweep solver renders here.")"""),
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
  Figs. 8, 16 (hard and soft shadows of polygons on volumes) — the splat solver, **not in
  this version**: its section runs once `difffog.SplatRenderer` exists."""),
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
## Zhang & Crawfis: clouds and soft shadows (the splat solver)

Their Figs. 1, 2 and 4 show the same clouds lit from behind with no multiple scattering, with
multiple forward scattering, and with forward and back scattering; Figs. 8 and 16 show the
hard and the soft (penumbra) shadows of polygon models on a volume. The shared `cloud-plane`
scene (a forward-scattering cloud, g = 0.85, under a polygon airplane) is the case they
are about; the sweep solver only approximates it (δ-isotropic scaling, 31% relative RMSE in
the oblique view at N = 64).

**Not in this version:** the splat solver is being written. The cell below renders these
figures when `difffog.SplatRenderer` exists and says so otherwise."""),
    code("""\
if hasattr(df, "SplatRenderer"):
    cloud = df.load_scene("cloud-plane")
    shots = {"Fig. 1-like: no multiple scattering": {"forward": False, "back": False},
             "Fig. 2-like: forward": {"forward": True, "back": False},
             "Fig. 4-like: forward and back": {"forward": True, "back": True}}
    imgs = {}
    for title, opts in shots.items():
        out = df.SplatRenderer(cloud, resolution=N, **opts).render()
        imgs |= {f"{title}\\n{k}": v for k, v in out.images.items()}
    display(plot.image_grid(imgs, ncols=len(cloud.cameras)))
else:
    print("difffog.SplatRenderer is not in this version: the Zhang & Crawfis figures "
          "will be made here once the splat solver lands.")"""),
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
