"""The differentiable parameters of a scene, and the dotted paths that name them.

``Params`` is the only pytree that gradients flow to: fog coefficients, the phase asymmetry,
per-shape albedo and emission, and the light intensities.  Geometry (shapes, sun direction,
the lattice) is static.  The same dotted paths serve ``--set`` overrides and the unknowns of
a fit: ``fog.scattering``, ``fog.absorption``, ``fog.g``, ``sun.irradiance``, ``sky.radiance``,
``shape.<name>.albedo``, ``shape.<name>.emission``; and, traced by the sweep solver only,
``fog.density`` (the density grid, an array: ``with_density``) and ``sun.zenith_deg``,
``sun.azimuth_deg`` (the sun's direction, for photographs whose sun is not known exactly).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._errors import SceneError
from ._description import Scene


class Params(eqx.Module):
    scattering: Float[Array, ""]  # ζ per unit length (multiplies the density grid)
    absorption: Float[Array, ""]  # γ per unit length
    g: Float[Array, ""]  # Henyey-Greenstein asymmetry (0 = isotropic)
    albedo: Float[Array, " shapes"]  # Lambertian reflectance ρ per shape, in scene order
    emission: Float[Array, " shapes"]  # emitted radiance per shape
    sun_irradiance: Float[Array, ""]
    sky_radiance: Float[Array, ""]
    # the fog's density grid as an unknown (cell-centred over the domain, [ix, iy, iz] as scene
    # files index it), or None: the scene's own density, fixed on the host.  Only the sweep
    # solver traces it (``with_density``; the lattice maps it by ``Lattice.density_map``).
    density: Float[Array, "gx gy gz"] | None = None
    # the sun's direction as unknowns (degrees, as the scene file's [sun]), or None: the scene's
    # own, fixed on the host.  Only the sweep solver traces them, in a model built with
    # ``with_sun_derivatives`` (its host-side sun quantities linearized about the scene's sun).
    sun_zenith: Float[Array, ""] | None = None
    sun_azimuth: Float[Array, ""] | None = None

    @classmethod
    def from_scene(cls, scene: Scene, dtype=None) -> "Params":
        dtype = dtype or jnp.result_type(float)
        f = scene.fog
        arr = lambda x: jnp.asarray(x, dtype=dtype)  # noqa: E731
        return cls(
            scattering=arr(f.scattering if f else 0.0),
            absorption=arr(f.absorption if f else 0.0),
            g=arr(f.g if (f and f.phase == "henyey-greenstein") else 0.0),
            albedo=arr([s.albedo for s in scene.shapes]).reshape(len(scene.shapes)),
            emission=arr([s.emission for s in scene.shapes]).reshape(len(scene.shapes)),
            sun_irradiance=arr(scene.sun.irradiance if scene.sun else 0.0),
            sky_radiance=arr(scene.sky.radiance if scene.sky else 0.0),
        )


_SCALAR_PATHS = {
    "fog.scattering": "scattering",
    "fog.absorption": "absorption",
    "fog.g": "g",
    "sun.irradiance": "sun_irradiance",
    "sky.radiance": "sky_radiance",
}


def with_density(params: Params, grid) -> Params:
    """``params`` with the fog's density grid ``grid`` (a 3-D array, cell-centred over the
    domain, indexed [ix, iy, iz]) as a traced parameter, in the parameters' dtype.

    The model maps it onto its lattice as it maps the scene's own grid (same shape); cells where
    the scene's grid is 0 must stay 0 (the light solve's and the cameras' work is restricted to
    where the scene's fog can be: fog appearing there is a discontinuity, not a derivative), as
    they do under a fit's log parameters (:func:`difffog.fit_density`)."""
    g = jnp.asarray(grid, dtype=params.scattering.dtype)
    if g.ndim != 3:
        raise SceneError(f"fog.density must be a 3-D grid [ix, iy, iz], got shape {g.shape}")
    return eqx.tree_at(lambda p: p.density, params, g, is_leaf=lambda x: x is None)


def param_paths(scene: Scene) -> list[str]:
    """Every dotted path of this scene that names a differentiable parameter (``fog.density``:
    the density grid, an array; the rest are scalars)."""
    out = list(_SCALAR_PATHS)
    if scene.fog is not None:
        out.append("fog.density")
    if scene.sun is not None:
        out += list(SUN_PATHS)
    for s in scene.shapes:
        out += [f"shape.{s.name}.albedo", f"shape.{s.name}.emission"]
    return out


#: the sun's direction: dotted path → ``Params`` field and the scene's ``Sun`` attribute
SUN_PATHS = {"sun.zenith_deg": ("sun_zenith", "zenith_deg"),
             "sun.azimuth_deg": ("sun_azimuth", "azimuth_deg")}
_SUN_FIELDS = {field: attr for field, attr in SUN_PATHS.values()}


def sun_direction_of(params: Params, scene: Scene):
    """The unit vector towards the sun (3,) from ``params``' traced angles (the scene's where
    only one is given), or None when neither is traced (the scene's, static)."""
    if scene.sun is None or (params.sun_zenith is None and params.sun_azimuth is None):
        return None
    dt = params.scattering.dtype
    zen = (jnp.asarray(scene.sun.zenith_deg, dt) if params.sun_zenith is None
           else params.sun_zenith.astype(dt))
    az = (jnp.asarray(scene.sun.azimuth_deg, dt) if params.sun_azimuth is None
          else params.sun_azimuth.astype(dt))
    t, p = jnp.deg2rad(zen), jnp.deg2rad(az)
    return jnp.stack([jnp.sin(t) * jnp.cos(p), jnp.sin(t) * jnp.sin(p), jnp.cos(t)])


def _locate(scene: Scene, path: str):
    if path in _SCALAR_PATHS:
        return _SCALAR_PATHS[path], None
    if path in SUN_PATHS and scene.sun is not None:
        return SUN_PATHS[path][0], None
    if path == "fog.density" and scene.fog is not None:
        return "density", None
    parts = path.split(".")
    if len(parts) == 3 and parts[0] == "shape" and parts[2] in ("albedo", "emission"):
        names = [s.name for s in scene.shapes]
        if parts[1] in names:
            return parts[2], names.index(parts[1])
    import difflib

    close = difflib.get_close_matches(path, param_paths(scene), n=1)
    hint = f" Did you mean '{close[0]}'?" if close else ""
    raise SceneError(
        f"'{path}' is not a differentiable parameter of scene '{scene.title}'.{hint} "
        f"Known: {', '.join(param_paths(scene))}"
    )


def get_param(params: Params, scene: Scene, path: str):
    leaf, idx = _locate(scene, path)
    v = getattr(params, leaf)
    if leaf == "density" and v is None:  # the scene's own grid (1 for a uniform fog)
        d = scene.fog.density
        return jnp.ones((1, 1, 1), params.scattering.dtype) if d is None else jnp.asarray(
            d, params.scattering.dtype)
    if leaf in _SUN_FIELDS and v is None:  # the scene's own
        return jnp.asarray(getattr(scene.sun, _SUN_FIELDS[leaf]), params.scattering.dtype)
    return v if idx is None else v[idx]


def set_param(params: Params, scene: Scene, path: str, value) -> Params:
    leaf, idx = _locate(scene, path)
    if leaf == "density":
        return with_density(params, value)
    if leaf in _SUN_FIELDS:
        new = jnp.asarray(value, dtype=params.scattering.dtype)
        return eqx.tree_at(lambda p: getattr(p, leaf), params, new, is_leaf=lambda x: x is None)
    if idx is None:
        new = jnp.asarray(value, dtype=getattr(params, leaf).dtype)
    else:
        new = getattr(params, leaf).at[idx].set(value)
    return eqx.tree_at(lambda p: getattr(p, leaf), params, new)
