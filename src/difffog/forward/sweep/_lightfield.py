"""What the sweep's light solve returns: the converged light on the lattice, for any camera."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from ..._numerics import trilinear
from .._model import AbstractLight


class LightField(AbstractLight):
    """The converged light of a scene on its lattice (all fields (nx, ny, nz), node (i, j, k)
    at ``origin + (idx + 0.5)·h``).

    fluence: Λ = Σ_L w_L R(x, L), the scattered (collided) light arriving at FREE nodes (W m⁻²
        for a sun irradiance in W m⁻²); the mean diffuse radiance is Λ/4π.
    sun_fluence: F·T_sun, the uncollided sun arriving at each node (irradiance on a plane
        perpendicular to the beam).
    sky_fluence: Σ_k w_k·sky·T_k, the uncollided sky arriving at each node (first-collision
        sky; zero when the sky is propagated through the lattice directions instead).
    radiosity: B, the Lambertian exitant radiance of SURFACE nodes (0 elsewhere).
    irradiance: the diffuse irradiance of SURFACE nodes (W m⁻²): all but the direct sun (the
        scattered light, the other surfaces, the uncollided sky), 0 elsewhere; the cameras'
        exact hits rebuild the radiosity from it with the exact direct sun.
    source: Q = (ζ/(ζ+γ))·J, the step source radiance at FREE nodes (isotropic part).
    residuals: (max_iterations,) relative change per iteration (NaN past ``iterations``).
    iterations: applications of the one-bounce operator (six sweeps each).
    error_estimate: the estimated remaining relative error when the iteration stopped.
    result: a :class:`difffog.RESULTS` code (int32).
    moments: with an anisotropic phase (``SweepSolver.phase_order`` L > 0), the K = (L+1)² − 1
        angular moments Σ_L w_L Ỹ_k(L̂) R of the scattered light (``_harmonics.Basis``), else
        None; sky_moments: those of the uncollided sky (None without a first-collision sky);
        once_source: with ``SweepSolver.once_M``, the anisotropic source per unit ζ' of the
        sun's once-scattered light swept on that finer direction set (in ``moments``' basis,
        what their δ-M coefficients g'_k times ``moments`` are for the rest; its fluence is in
        ``fluence``), else None.
    source_slope: with the linear-source scheme (``SweepSolver.scheme``), h∇Q: the isotropic
        source's change per lattice spacing along x, y, z (nx, ny, nz, 3), else None;
        fluence_slope: h∇(Λ + sky_fluence), the scattered light's (what the cameras' in-scatter
        reads besides the sun's single scattering), likewise.
    dip: the most negative fluence of the solve's fixed point as a share of its largest
        (≥ 0; ``fluence`` holds it clipped to 0): the linear scheme's where one lattice step
        spans many mean free paths (issue 14's cube at N = 8, ζ = 100: 0.11); GMRES's residual
        elsewhere (~tol).  ``difffog.render`` warns above 1% (``forward._model.DIP_WARNING``).
    sun_peak: with an anisotropic phase, (kept, c, width): the share of the sun's first
        collision that its beam keeps, the forward peak that the lattice's directions cannot
        resolve and would carry off course (``_solver._cell_phase``), so the beam,
        ``sun_fluence``, is attenuated by ζ(1 − kept) + γ; the light leaving it scatters with
        p·(1 − c·K), K = ``forward_peak_kernel``(cos Θ, width): the cameras read the sun
        alike; else None.
    state: the light solve's own state at its fixed point, (Λ [with the moments as channels],
        E: the SURFACE nodes' scattered irradiance), before the clip to Λ ≥ 0: what a solve of
        a nearby problem on the same model starts from (``SweepModel.light(params,
        init=light.state)``: the model error's next render of its fine model), or None.
    origin, h: the lattice's lower corner and spacing (static).
    """

    fluence: Float[Array, "nx ny nz"]
    sun_fluence: Float[Array, "nx ny nz"]
    sky_fluence: Float[Array, "nx ny nz"]
    radiosity: Float[Array, "nx ny nz"]
    irradiance: Float[Array, "nx ny nz"]
    source: Float[Array, "nx ny nz"]
    residuals: Float[Array, " max_iters"]
    iterations: Int[Array, ""]
    error_estimate: Float[Array, ""]
    result: Int[Array, ""]
    moments: Float[Array, "nx ny nz K"] | None = None
    sky_moments: Float[Array, "nx ny nz K"] | None = None
    once_source: Float[Array, "nx ny nz K"] | None = None
    source_slope: Float[Array, "nx ny nz 3"] | None = None
    fluence_slope: Float[Array, "nx ny nz 3"] | None = None
    dip: Float[Array, ""] | None = None
    sun_peak: Float[Array, "3"] | None = None
    state: tuple[Array, Array] | None = None
    origin: tuple[float, float, float] = eqx.field(static=True, default=(0.0, 0.0, 0.0))
    h: float = eqx.field(static=True, default=1.0)

    def fluence_at(self, points: Float[Array, "... 3"]) -> Float[Array, "..."]:
        """Total fluence (collided Λ + uncollided sun + uncollided sky) at world points,
        trilinear between nodes, 0 outside the lattice."""
        total = self.fluence + self.sun_fluence + self.sky_fluence
        pts = jnp.asarray(points, total.dtype)
        return trilinear(total, self.origin, self.h, pts)

    def report(self) -> dict:
        k = int(self.iterations)
        return {"iterations": k,
                "residuals": [float(x) for x in jax.device_get(self.residuals)[:k]],
                "error_estimate": float(self.error_estimate)}
