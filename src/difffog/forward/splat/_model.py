"""The splat forward model: every camera is one pass over sheets (``_pass.py``), set up once on
the host (``_sheets.py``).  The light is the sheets' streams of that pass, so the splat's
"light" and its images come out of the same scan."""

from __future__ import annotations

import time
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from ..._errors import SceneError
from ..._numerics import bilinear
from ..._results import RESULTS
from ...geometry._lattice import Lattice, voxelize
from ...geometry._rays import scene_triangles
from ...scene._description import Camera, Scene
from ...scene._params import Params
from .._model import AbstractForwardModel, AbstractLight, HostInfo, select_cameras
from ._pass import splat_pass
from ._sheets import SheetFrame, SheetGeometry, build_sheets


class SheetLight(AbstractLight):
    """The light of a splat render: per camera pass, the light entering each of its K sheets
    along the sun, and the images composited in the same pass.

    images: {camera: (H, W)} (the pass renders light and image together).
    direct, forward, back: per camera, (K, hs, ws) intensities of the direct, the
        forward-scattered and the back-scattered streams entering each sheet (units of the
        sun's irradiance), on the shadow buffer's texels.
    tau: per camera, (K, hs, ws) optical depth of each sheet along the light rays.
    frames: per camera, where its sheets lie (static).
    result, iterations, error_estimate: one direct pass: ``nonfinite`` if any image is not
        finite, else successful; 1; 0.
    """

    images: dict[str, Float[Array, "H W"]]
    direct: tuple[Float[Array, "K hs ws"], ...]
    forward: tuple[Float[Array, "K hs ws"], ...]
    back: tuple[Float[Array, "K hs ws"], ...]
    tau: tuple[Float[Array, "K hs ws"], ...]
    result: Int[Array, ""]
    iterations: Int[Array, ""]
    error_estimate: Float[Array, ""]
    frames: tuple[SheetFrame, ...] = eqx.field(static=True)

    def streams_at(self, points, camera: int = 0):
        """(direct, forward-scattered, back) light intensity at world points (..., 3), read
        from camera pass ``camera``'s sheets (each pass has its own sheets; the light is the
        same up to their discretization).  Points before the first sheet read it
        unattenuated, points past the last read the last slab's exit."""
        fr = self.frames[camera]
        Fd, Fs, B, tau = (x[camera] for x in (self.direct, self.forward, self.back, self.tau))
        dt = Fd.dtype
        x = jnp.asarray(points, dt)
        s, a, b, L = (jnp.asarray(v, dt) for v in (fr.s, fr.a, fr.b, fr.L))
        K = Fd.shape[0]
        z = (x @ s - fr.z_lo) / fr.dz
        k = jnp.clip(jnp.floor(z), 0, K - 1).astype(jnp.int32)
        f = jnp.clip(z - k, 0.0, 1.0)
        xp = x - (x @ s / (s @ L))[..., None] * L
        u = (xp @ a - fr.u_min) / fr.texel - 0.5
        v = (xp @ b - fr.v_min) / fr.texel - 0.5

        def at(buf):
            return _pick(buf, k, u, v)

        t = at(tau)
        return at(Fd) * jnp.exp(-t * f), at(Fs) * jnp.exp(-t * f), at(B) * jnp.exp(-t * (1 - f))

    def fluence_at(self, points):
        d, f, b = self.streams_at(points)
        return d + f + b

    def report(self) -> dict:
        return {"iterations": int(self.iterations), "passes": len(self.frames),
                "sheets": [int(x.shape[0]) for x in self.direct]}


def _pick(buf, k, u, v):
    """Bilinear lookup in sheet k (per point) of a (K, hs, ws) buffer, clamped."""
    return jax.vmap(lambda kk, uu, vv: bilinear(buf[kk], uu, vv))(
        k.reshape(-1), u.reshape(-1), v.reshape(-1)).reshape(k.shape)


class SplatModel(AbstractForwardModel):
    """The splat's forward model (final): Zhang & Crawfis' sheet-based splatting, one pass
    per camera.  Build it with :func:`difffog.forward_model` (``solver="splat"``) or directly:

    scene: the scene (open boundary, with a [sun]).
    resolution: lattice nodes along the longest domain axis (the voxels that are splatted).
    sheets: slices per camera pass (default: one per voxel spacing along the half-way
        vector): the accuracy knob.
    cameras: names (or Camera objects) of the cameras to render (default: all).
    supersample: s×s rays per pixel (box filter).
    forward_scatter, back_scatter: the paper's §3 multiple-scattering terms (both off:
        attenuation only).
    soft_shadows: §5 (the sun's ``angular_radius_deg`` sets the penumbra; also widens the
        sheets to cover the polygons).
    back_window: W, the stored sheets below a sheet that scatter back into it.
    shadow_texel: shadow-buffer texel size (scene units; default the voxel size).
    quadrature: Gauss–Legendre points per footprint segment.
    kernel_radius: scattering kernels of (2R+1)² texels.
    occluder_thickness: "paper" (∝ 1/|∇z_light|, §5, scaled by ``thickness_scale`` texels)
        or "exact" (the occluder's own extent along the light).
    scattered_phase: "hg" (the paper: scattered light seen through the fog's phase about the
        light direction) or "isotropic".
    similarity: propagate the sheets with ζ(1−g) and isotropic kernels (default; see
        :func:`splat_pass`); False: the paper's HG kernels (cloud-plane vs Mitsuba: 13% / 37%
        error with it, 26% / 57% without).
    """

    scene: Scene = eqx.field(static=True)
    cameras: tuple[Camera, ...] = eqx.field(static=True)
    passes: tuple[SheetGeometry, ...]
    resolution: int = eqx.field(static=True)
    sheets: int | None = eqx.field(static=True)
    supersample: int = eqx.field(static=True)
    options: tuple[tuple[str, object], ...] = eqx.field(static=True)
    host: HostInfo = eqx.field(static=True)

    def __init__(self, scene: Scene, *, resolution: int = 64, sheets: int | None = None,
                 cameras=None, supersample: int = 1, forward_scatter: bool = True,
                 back_scatter: bool = True, soft_shadows: bool = True, back_window: int = 6,
                 shadow_texel: float | None = None, quadrature: int = 2,
                 kernel_radius: int = 3, occluder_thickness: str = "paper",
                 thickness_scale: float = 4.0, scattered_phase: str = "hg",
                 similarity: bool = True):
        if scene.domain.boundary != "open":
            raise SceneError(f"scene '{scene.title}': boundary '{scene.domain.boundary}' is not "
                             "supported by the splat solver (its sheets are finite); use "
                             "boundary = \"open\" or the sweep solver")
        if scene.sun is None:
            raise SceneError(f"scene '{scene.title}' has no [sun]: the splat solver propagates "
                             "one directional light (Zhang & Crawfis); add a [sun] or use the "
                             "sweep solver")
        for name, v, lo in (("resolution", resolution, 2), ("supersample", supersample, 1),
                            ("quadrature", quadrature, 1), ("kernel_radius", kernel_radius, 1),
                            ("back_window", back_window, 1)):
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
                raise SceneError(f"splat: {name} must be an integer ≥ {lo}, got {v!r}")
        if sheets is not None and (isinstance(sheets, bool)
                                   or not isinstance(sheets, (int, np.integer)) or sheets < 1):
            raise SceneError(f"splat: sheets must be a positive integer (or None for one per "
                             f"voxel), got {sheets!r}")
        if occluder_thickness not in ("paper", "exact"):
            raise SceneError(f"splat: occluder_thickness must be 'paper' or 'exact', got "
                             f"{occluder_thickness!r}")
        if scattered_phase not in ("hg", "isotropic"):
            raise SceneError(f"splat: scattered_phase must be 'hg' or 'isotropic', got "
                             f"{scattered_phase!r}")
        self.scene = scene
        self.resolution = int(resolution)
        self.sheets = None if sheets is None else int(sheets)
        self.supersample = int(supersample)
        opts = dict(forward_scatter=bool(forward_scatter), back_scatter=bool(back_scatter),
                    soft_shadows=bool(soft_shadows), back_window=int(back_window),
                    shadow_texel=shadow_texel, quadrature=int(quadrature),
                    kernel_radius=int(kernel_radius), occluder_thickness=occluder_thickness,
                    thickness_scale=float(thickness_scale), scattered_phase=scattered_phase,
                    similarity=bool(similarity))
        self.options = tuple(opts.items())
        self.cameras = select_cameras(scene, cameras)
        t = time.perf_counter()
        with warnings.catch_warnings():
            # the lattice only carries the fog density here (fog minus solids); the polygons
            # are rasterized, so the voxelizer's "shape thinner than a voxel" warning does not
            # apply
            warnings.filterwarnings("ignore", message="shape .* thick, less than one voxel")
            lattice = voxelize(scene, self.resolution, 1, margin=1)
        triangles = scene_triangles(scene)
        voxelize_s = time.perf_counter() - t
        t = time.perf_counter()
        built = [build_sheets(scene, lattice, triangles, c, sheets=self.sheets,
                              supersample=self.supersample,
                              back_window=back_window if back_scatter else 0,
                              forward=forward_scatter, soft=soft_shadows,
                              shadow_texel=shadow_texel, quadrature=quadrature,
                              kernel_radius=kernel_radius,
                              occluder_thickness=occluder_thickness,
                              thickness_scale=thickness_scale)
                 for c in self.cameras]
        self.passes = tuple(b[0] for b in built)
        self.host = HostInfo(lattice=lattice, triangles=triangles,
                             pass_info={c.name: b[1] for c, b in zip(self.cameras, built)},
                             setup_s={"voxelize_s": voxelize_s,
                                      "prepare_s": time.perf_counter() - t})

    @property
    def lattice(self) -> Lattice:
        return self.host.lattice

    def _pass_options(self) -> dict:
        o = dict(self.options)
        return {"scattered_phase": o["scattered_phase"], "similarity": o["similarity"]}

    def check(self, params: Params) -> None:
        _no_density(params)

    def light(self, params: Params) -> SheetLight:
        _no_density(params)
        images, streams = {}, []
        for cam, geo in zip(self.cameras, self.passes):
            img, ys = splat_pass(geo, params, return_light=True, **self._pass_options())
            images[cam.name] = img
            streams.append(ys)
        o = dict(self.options)
        zeta = params.scattering * (1.0 - params.g) if o["similarity"] else params.scattering
        sig = zeta + params.absorption
        finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(v)) for v in images.values()]))
        dt = params.scattering.dtype
        return SheetLight(
            images=images,
            direct=tuple(y[0] for y in streams),
            forward=tuple(y[1] for y in streams),
            back=tuple(y[2] for y in streams),
            tau=tuple(sig * g.light_D[:g.K].astype(dt) for g in self.passes),
            result=jnp.where(finite, RESULTS.successful, RESULTS.nonfinite).astype(jnp.int32),
            iterations=jnp.asarray(1, jnp.int32),
            error_estimate=jnp.asarray(0.0, dt),
            frames=tuple(g.frame for g in self.passes),
        )

    def images_from(self, light: SheetLight, params: Params) -> dict[str, jax.Array]:
        return dict(light.images)

    def settings(self) -> dict:
        lat = self.lattice
        return {
            "scene": self.scene.title,
            "solver": "splat",
            "solver_options": {"sheets": self.sheets, **dict(self.options)},
            "resolution": self.resolution,
            "lattice_shape": list(lat.shape),
            "voxel_size": lat.h,
            "triangles": len(self.host.triangles),
            "supersample": self.supersample,
            "cameras": [c.name for c in self.cameras],
            "passes": self.host.pass_info,
            "dtype": str(jnp.result_type(float)),
            "setup_s": dict(self.host.setup_s),
        }


def _no_density(params: Params) -> None:
    if params.density is not None:
        raise SceneError("fog.density: the splat solver takes the scene's density grid as "
                         "fixed and does not trace it; render or fit a density with the sweep "
                         "solver (forward_model(scene, \"sweep\"))")
    if params.sun_zenith is not None or params.sun_azimuth is not None:
        raise SceneError("sun.zenith_deg / sun.azimuth_deg: the splat solver takes the sun's "
                         "direction as fixed (its sheets are built facing it); fit the sun with "
                         "the sweep solver (forward=\"sweep\")")
