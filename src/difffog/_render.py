"""The pipeline in one call: scene → lattice → light solve → images of every camera.

One light solve serves every camera.  ``Renderer`` keeps the host-side work (voxelization, the
solver's static geometry, the camera extension maps) so that re-rendering with new parameters —
what a fit does at every step — only runs the JAX part.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from scipy import ndimage

from ._camera import LatticeFields, render_camera
from ._errors import SceneError
from ._lattice import SOLID, SURFACE, voxelize
from ._lightfield import LightField
from ._params import Params
from ._plan import check_params
from ._scene import Scene
from ._solver import AbstractLightSolver, SweepSolver

FOUR_PI = 4.0 * math.pi


def _nearest_index(mask: np.ndarray, periodic_xy: bool) -> np.ndarray:
    """For every node, the flat index of the nearest node where ``mask`` is True."""
    if not mask.any():
        return np.zeros(mask.shape, np.int64)
    _, idx = ndimage.distance_transform_edt(~mask, return_indices=True)
    return np.ravel_multi_index(tuple(idx), mask.shape)


class CameraGeometry(eqx.Module):
    """Static maps that extend solver fields to every node for trilinear camera lookups."""

    near_fluid: jax.Array  # flat index of the nearest non-SOLID node
    near_surface: jax.Array  # flat index of the nearest SURFACE node
    normal: jax.Array  # (nx, ny, nz, 3) unit normals at SURFACE nodes, 0 elsewhere
    sdf: jax.Array
    origin: tuple[float, float, float] = eqx.field(static=True)
    h: float = eqx.field(static=True)
    sun_dir: tuple[float, float, float] | None = eqx.field(static=True)
    periodic_xy: bool = eqx.field(static=True)
    has_surfaces: bool = eqx.field(static=True)

    @classmethod
    def build(cls, scene: Scene, lattice) -> "CameraGeometry":
        nt = np.asarray(lattice.node_type)
        periodic = lattice.boundary == "periodic-xy"
        surf = nt == SURFACE
        return cls(
            near_fluid=jnp.asarray(_nearest_index(nt != SOLID, periodic)),
            near_surface=jnp.asarray(_nearest_index(surf, periodic)),
            sdf=jnp.asarray(lattice.sdf, jnp.float32),
            normal=jnp.asarray(np.where(surf[..., None], lattice.normal, 0.0), jnp.float32),
            origin=tuple(float(x) for x in lattice.origin),
            h=float(lattice.h),
            sun_dir=None if scene.sun is None else tuple(float(x) for x in scene.sun.direction),
            periodic_xy=periodic,
            has_surfaces=bool(surf.any()),
        )


def camera_fields(cam: CameraGeometry, density, light: LightField, params: Params) -> LatticeFields:
    """The node fields a camera marches through, from a converged light field.

    Extinction and the isotropic source use the solver's δ-isotropic scaling ζ' = ζ(1−g) (exact
    for g = 0); the sun's single scattering uses the full ζ with the Henyey–Greenstein phase.
    Values are extended from the nearest fluid node into solids and from the nearest SURFACE
    node for the radiosity, so that trilinear interpolation near a surface stays sensible.
    """
    dt = params.scattering.dtype
    ext = lambda a, idx: a.reshape(-1)[idx]  # noqa: E731
    dens = ext(density.astype(dt), cam.near_fluid)
    zeta_r = params.scattering * (1.0 - params.g)
    sigma_t = (zeta_r + params.absorption) * dens
    j_iso = zeta_r * dens * ext(light.fluence + light.sky_fluence, cam.near_fluid) / FOUR_PI
    j_sun = params.scattering * dens * ext(light.sun_fluence, cam.near_fluid)
    if cam.has_surfaces:
        rad = ext(light.radiosity, cam.near_surface)
    else:
        rad = jnp.zeros_like(sigma_t)
    return LatticeFields(
        sigma_t=sigma_t,
        j_iso=j_iso,
        j_sun=j_sun,
        radiosity_ext=rad,
        sdf=cam.sdf.astype(dt),
        origin=cam.origin,
        h=cam.h,
        g=params.g,
        sun_dir=cam.sun_dir,
        sky=params.sky_radiance,
        periodic_xy=cam.periodic_xy,
        surface_normal=cam.normal.astype(dt) if cam.has_surfaces else None,
    )


@dataclass
class Rendered:
    """Images (H, W) keyed by camera name, the light field and what it took.

    ``light`` is the solver's light: a :class:`LightField` for the sweep; for the splat solver
    (which needs no 3-D light volume) a summary of each camera's pass (sheets, buffer, order).
    """

    images: dict[str, np.ndarray]
    light: LightField | dict | None = None
    timings: dict[str, float] = field(default_factory=dict)
    settings: dict = field(default_factory=dict)


class Renderer:
    """A scene prepared for repeated renders: ``renderer(params)`` → images.

    resolution: lattice nodes along the longest domain axis; solver: a light solver (default
    ``SweepSolver(M=3)``); supersample: s×s stratified rays per pixel (box filter).
    """

    def __init__(self, scene: Scene, *, resolution: int = 64, solver: AbstractLightSolver | None = None,
                 supersample: int = 2, cameras: list[str] | None = None):
        self.scene = scene
        self.solver = solver if solver is not None else SweepSolver()
        self.supersample = int(supersample)
        self.resolution = int(resolution)
        names = [c.name for c in scene.cameras] if cameras is None else list(cameras)
        self.cameras = [scene.camera(n) for n in names]
        self.timings: dict[str, float] = {}
        t = time.perf_counter()
        M = getattr(self.solver, "M", 1)
        self.lattice = voxelize(scene, resolution, M, margin=M + 1)
        self.timings["voxelize_s"] = time.perf_counter() - t
        t = time.perf_counter()
        self.geometry = self.solver.prepare(scene, self.lattice)
        self.cam_geometry = CameraGeometry.build(scene, self.lattice)
        self.density = jnp.asarray(self.lattice.density, jnp.float32)
        self.timings["prepare_s"] = time.perf_counter() - t
        self._solve = jax.jit(self.solver.solve)
        # The static arrays (solver geometry, camera maps, density) go in as arguments, not as
        # closed-over constants: XLA would otherwise constant-fold them at every compile
        # (seconds at N = 64, the "slow constant folding" alarm).
        self._images = jax.jit(self._images_with)
        self._forward = jax.jit(self._forward_with)

    def params(self, dtype=None) -> Params:
        return Params.from_scene(self.scene, dtype)

    def _check(self, params: Params) -> None:
        """Concrete parameters against the solver's plan: a SolverError (one line) here rather
        than a runtime error from inside the compiled solve."""
        plan = getattr(self.geometry, "plan", None)
        if plan is not None:
            check_params(plan, params)

    def solve(self, params: Params) -> LightField:
        self._check(params)
        return self._solve(self.geometry, params)

    def _images_with(self, cam_geometry, density, light: LightField, params: Params):
        f = camera_fields(cam_geometry, density, light, params)
        return {c.name: render_camera(f, c, supersample=self.supersample) for c in self.cameras}

    def _forward_with(self, geometry, cam_geometry, density, params: Params):
        return self._images_with(cam_geometry, density, self.solver.solve(geometry, params),
                                 params)

    def _images_impl(self, light: LightField, params: Params):
        return self._images_with(self.cam_geometry, self.density, light, params)

    def images(self, light: LightField, params: Params) -> dict[str, jax.Array]:
        return self._images(self.cam_geometry, self.density, light, params)

    def _forward_impl(self, params: Params):
        return self._forward_with(self.geometry, self.cam_geometry, self.density, params)

    def __call__(self, params: Params | None = None) -> dict[str, jax.Array]:
        """Differentiable (and jitted): images of every camera for these parameters."""
        params = self.params() if params is None else params
        self._check(params)
        return self._forward(self.geometry, self.cam_geometry, self.density, params)

    def render(self, params: Params | None = None) -> Rendered:
        """Solve and render every camera, timing each stage (compile included, reported apart)."""
        params = self.params() if params is None else params
        self._check(params)
        timings = dict(self.timings)
        t = time.perf_counter()
        compiled = self._solve.lower(self.geometry, params).compile()
        timings["solve_compile_s"] = time.perf_counter() - t
        t = time.perf_counter()
        light = jax.block_until_ready(compiled(self.geometry, params))
        timings["solve_s"] = time.perf_counter() - t
        t = time.perf_counter()
        static = (self.cam_geometry, self.density)
        compiled_img = self._images.lower(*static, light, params).compile()
        timings["render_compile_s"] = time.perf_counter() - t
        t = time.perf_counter()
        imgs = jax.block_until_ready(compiled_img(*static, light, params))
        timings["render_s"] = time.perf_counter() - t
        images = {k: np.asarray(v, np.float32) for k, v in imgs.items()}
        for k, v in images.items():
            if not np.all(np.isfinite(v)):
                raise SceneError(f"camera '{k}': the image has non-finite values (a solver bug?)")
        return Rendered(images=images, light=light, timings=timings, settings=self.settings())

    def settings(self) -> dict:
        lat = self.lattice
        return {
            "scene": self.scene.title,
            "solver": type(self.solver).__name__,
            "solver_options": {
                k: getattr(self.solver, k)
                for k in ("M", "method", "max_iterations", "tol", "sky_quadrature", "terms")
                if hasattr(self.solver, k)
            },
            "resolution": self.resolution,
            "lattice_shape": list(lat.shape),  # includes the vacuum margin around open sides
            "voxel_size": lat.h,
            "node_counts": lat.counts(),
            "supersample": self.supersample,
            "cameras": [c.name for c in self.cameras],
            "dtype": str(jnp.result_type(float)),
            "plan": ([] if getattr(self.geometry, "plan", None) is None
                     else self.geometry.plan.lines(lat.shape)),
        }


def render(scene: Scene, *, resolution: int = 64, solver: AbstractLightSolver | None = None,
           params: Params | None = None, cameras: list[str] | None = None,
           supersample: int = 2) -> Rendered:
    """Render every camera of ``scene`` (or those named) with one light solve."""
    return Renderer(scene, resolution=resolution, solver=solver, supersample=supersample,
                    cameras=cameras).render(params)
