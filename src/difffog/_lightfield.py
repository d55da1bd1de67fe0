"""What a light solver returns: the converged light in the lattice, ready for any camera."""

from __future__ import annotations

import equinox as eqx
import jax
from jaxtyping import Array, Float, Int


class LightField(eqx.Module):
    """The converged light of a scene on its lattice (all arrays (nx, ny, nz)).

    fluence: Λ = Σ_L w_L R(x, L), the scattered (collided) light arriving at FREE nodes, W/m²
        — the mean diffuse radiance is Λ/4π.
    sun_fluence: F·T_sun, the uncollided sun arriving at each node (irradiance on a plane
        perpendicular to the beam).
    sky_fluence: Σ_k w_k·sky·T_k, the uncollided sky light arriving at each node (first-collision
        sky; zero when the sky is propagated through the lattice directions instead).
    radiosity: B, the Lambertian exitant radiance of SURFACE nodes (0 elsewhere).
    source: Q = (ζ/(ζ+γ))·J, the step source radiance at FREE nodes (isotropic part).
    residuals: relative change of the solution per iteration (NaN past ``iterations``).
    iterations: Jacobi iterations run.
    """

    fluence: Float[Array, "nx ny nz"]
    sun_fluence: Float[Array, "nx ny nz"]
    sky_fluence: Float[Array, "nx ny nz"]
    radiosity: Float[Array, "nx ny nz"]
    source: Float[Array, "nx ny nz"]
    residuals: Float[Array, " max_iters"]
    iterations: Int[Array, ""]
    error_estimate: Float[Array, ""] = eqx.field(default_factory=lambda: jax.numpy.asarray(0.0))
