"""The differentiable parameters of a scene, and the dotted paths that name them.

``Params`` is the only pytree that gradients flow to: fog coefficients, the phase asymmetry,
per-shape albedo and emission, and the light intensities.  Geometry (shapes, sun direction,
the lattice) is static.  The same dotted paths serve ``--set`` overrides and the unknowns of
a fit: ``fog.scattering``, ``fog.absorption``, ``fog.g``, ``sun.irradiance``, ``sky.radiance``,
``shape.<name>.albedo``, ``shape.<name>.emission``.
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


def param_paths(scene: Scene) -> list[str]:
    """Every dotted path of this scene that names a differentiable parameter."""
    out = list(_SCALAR_PATHS)
    for s in scene.shapes:
        out += [f"shape.{s.name}.albedo", f"shape.{s.name}.emission"]
    return out


def _locate(scene: Scene, path: str):
    if path in _SCALAR_PATHS:
        return _SCALAR_PATHS[path], None
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
    return v if idx is None else v[idx]


def set_param(params: Params, scene: Scene, path: str, value) -> Params:
    leaf, idx = _locate(scene, path)
    if idx is None:
        new = jnp.asarray(value, dtype=getattr(params, leaf).dtype)
    else:
        new = getattr(params, leaf).at[idx].set(value)
    return eqx.tree_at(lambda p: getattr(p, leaf), params, new)
