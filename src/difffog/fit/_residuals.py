"""The fit's residuals and their Jacobian.

The residual is √w·(model − target)/RMS(target) over every target pixel of every view,
optionally rescaled by a robust loss.  Its Jacobian (pixels × unknowns) is computed once per
evaluated point by forward mode: each of its n columns costs one tangent light solve (the
implicit derivative of the fixed point, all n at once, their products matrix-free:
``SweepSolver.tangents``) and one forward-mode pass of the cameras; reverse mode would need
one adjoint solve per *pixel*.  The sweep's camera march has a hand-written reverse pass
(``jax.custom_vjp``) and no JVP rule, so the columns are traced inside ``forward_mode()``,
where the march is the plain scan.  (Until stop 42 the whole column was the transpose of the
whole VJP: the light's part then ran the adjoint's linearised operator transposed back, which
kept the linearised sweeps, 4.0 against 1.8 GiB at N = 24, ``benchmarks/fit_memory.py``;
until stop 60 the cameras' part still was, ``jax.linear_transpose`` of their VJP: 1.05 s for
the README example's three columns at N = 28, 7× its forward render.)  The
residual handed to optimistix is a ``jax.custom_jvp`` function whose tangent is ``J @ t`` with
that J, so optimistix materialises J once per step and its state stays an array pytree
(what a checkpoint stores): J, the residual and, in its aux, the images, the light state and
its n tangents at the accepted point (since stop 61; the next step's tangent solves start
from them), n + 1 copies of the light state (0.4 MB each for the README example, 25 MB for
cloud-plane at N = 64 with its moments).

The forward model travels in the optimizer's ``args`` (its arrays are arguments of the
compiled step, not constants), beside the per-fit data.
"""

from __future__ import annotations

from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._results import RESULTS
from ..forward.sweep._march import forward_mode
from ..scene._description import Scene
from ..scene._params import Params, set_param
from ._unknowns import Coordinate, exposure_camera

LOSSES = ("linear", "huber", "soft_l1", "cauchy")


def robust_factor(z, loss: str):
    """sqrt(ρ(z)/z) for z = (r/c)² ≥ 0: the residual r becomes r·factor so that Σ r̃² = c²Σρ."""
    if loss == "linear":
        return jnp.ones_like(z)
    if loss == "soft_l1":  # ρ = 2(√(1+z) − 1) → ρ/z = 2/(√(1+z) + 1)
        return jnp.sqrt(2.0 / (jnp.sqrt(1.0 + z) + 1.0))
    if loss == "huber":  # ρ = z (z ≤ 1), 2√z − 1
        big = z > 1.0
        zs = jnp.where(big, z, 1.0)
        return jnp.sqrt(jnp.where(big, (2.0 * jnp.sqrt(zs) - 1.0) / zs, 1.0))
    if loss == "cauchy":  # ρ = log(1+z)
        small = z < 1e-6
        zs = jnp.where(small, 1.0, z)
        return jnp.sqrt(jnp.where(small, 1.0 - z / 2.0, jnp.log1p(zs) / zs))
    raise AssertionError(loss)


@dataclass(frozen=True, eq=False)
class FitProblem:
    """The static part of a fit (hashed by identity): which parameters the unknowns u set, the
    cameras in the order their images are flattened, and the loss.

    scene: the forward model's scene (for the dotted paths).
    coords: one :class:`Coordinate` per unknown: a scene parameter, or an exposure (a gain on
        every camera's image, or one camera's) applied to the rendered images.
    names: target cameras, in the order of the flattened images.
    loss: one of ``LOSSES``.
    """

    scene: Scene
    coords: tuple[Coordinate, ...]
    names: tuple[str, ...]
    loss: str

    def params(self, u, base: Params) -> Params:
        p = base
        for i, c in enumerate(self.coords):
            if exposure_camera(c.path) is None:
                p = set_param(p, self.scene, c.path, c.to_v(u[i]))
        return p

    def gains(self, u) -> dict:
        """{camera: the product of the exposures that scale its image} (1.0 where none do)."""
        out = {n: 1.0 for n in self.names}
        for i, c in enumerate(self.coords):
            cam = exposure_camera(c.path)
            if cam is not None:
                for n in self.names:
                    if cam in ("", n):
                        out[n] = out[n] * c.to_v(u[i])
        return out

    def images_from(self, model, light, p: Params, u):
        """The flattened images (P,) from ``light`` at parameters ``p`` (``params(u, ...)``)
        times the exposures of unknowns u."""
        imgs = model.images_from(light, p)
        g = self.gains(u)
        return jnp.concatenate([g[n] * jnp.ravel(imgs[n]) for n in self.names])

    def model(self, model, u, base: Params, init=None):
        """(flattened images (P,) times their exposures, the light solve's result code, its
        light state) at unknowns u.  The light state is what a later light solve of the same
        model can start from (``init``): the sweep's ``LightField.state``, a constant of the
        solve; None for a model whose light has none."""
        p = self.params(u, base)
        light = _light(model, p, init)
        return self.images_from(model, light, p, u), light.result, getattr(light, "state", None)

    def model_and_jacobian(self, model, u, base: Params, guess=None):
        """(images (P,), J (P, n), result code) by forward mode: the light field's tangents by
        ``jax.jvp`` (one tangent light solve per unknown, all at once), then each column
        through the cameras by ``jax.jvp`` too (``forward_mode``).  ``guess``: see
        :meth:`jacobian_and_tangents`."""
        return tuple(self.jacobian_and_tangents(model, u, base, guess)[:3])

    def jacobian_and_tangents(self, model, u, base: Params, guess=None):
        """:meth:`model_and_jacobian`, the light state's tangents (n, *state): column k is
        ∂(light state)/∂u_k, where the tangent solves of a later call at a nearby u may start
        (``guess``; None: from zero), and the light state at u (``LightField.state``).  For a
        model without a light state (``zero_light_state`` None) both are None and ``guess``
        is not used."""
        n = u.shape[0]
        eye = jnp.eye(n, dtype=u.dtype)
        s0 = model.zero_light_state(u.dtype)
        if s0 is not None and guess is None:
            guess = tangent_start(model, n, u.dtype)

        def light_of(x, s):
            return _light(model, self.params(x, base), s)

        with forward_mode():  # the light's init tangent starts its tangent solves
            if s0 is None:
                light, dots = jax.vmap(lambda e: jax.jvp(lambda x: light_of(x, None), (u,), (e,)),
                                       out_axes=(None, 0))(eye)
            else:
                light, dots = jax.vmap(lambda e, g: jax.jvp(light_of, (u, s0), (e, g)),
                                       out_axes=(None, 0))(eye, guess)
        tangents = None if s0 is None else dots.state
        floats, rest = eqx.partition(light, eqx.is_inexact_array)
        d_floats = eqx.filter(dots, eqx.is_inexact_array)

        def images(fl, x):
            return self.images_from(model, eqx.combine(fl, rest), self.params(x, base), x)

        with forward_mode():  # the cameras' marches as plain scans, which jax.jvp can take
            y, cols = jax.vmap(lambda t, e: jax.jvp(images, (floats, u), (t, e)),
                               out_axes=(None, 0))(d_floats, eye)
        state = None if s0 is None else jax.tree.map(jax.lax.stop_gradient, light.state)
        # a tangent solve that did not converge returns NaN (``_implicit._fixed_point_jvp``):
        # its code, and zeros where the Jacobian and the next start would hold NaN
        J = cols.T
        finite = jnp.all(jnp.isfinite(J))
        code = jnp.where(finite | (light.result != RESULTS.successful), light.result,
                         RESULTS.tangent_unconverged).astype(jnp.int32)
        J = jnp.where(jnp.isfinite(J), J, 0.0)
        if tangents is not None:
            tangents = jax.tree.map(lambda a: jnp.where(jnp.isfinite(a), a, 0.0), tangents)
        return y, J, code, tangents, state


def tangent_start(model, n: int, dtype):
    """n zero light-state tangents (the tangent solves' start without a guess), or None for a
    model without a light state."""
    s0 = model.zero_light_state(dtype)
    if s0 is None:
        return None
    return jax.tree.map(lambda a: jnp.zeros((n,) + a.shape, a.dtype), s0)


def _light(model, p: Params, init):
    """The model's light at p, started from ``init`` where there is one (a model whose light
    has a ``state`` takes ``light(p, init=...)``; any other is called as the interface
    defines it)."""
    return model.light(p) if init is None else model.light(p, init=init)


def _model_cj(problem: FitProblem, model, u, base: Params, guess):
    """The images and result code at u, with the tangent J·t of the images from
    :meth:`FitProblem.jacobian_and_tangents` (the result code has no tangent), and the light
    state's tangents there (n, *state), the next evaluation's ``guess`` (the tangent solves
    start from the last evaluation's tangents, which a nearby point's solves then reach in
    fewer GMRES steps; their path-dependent error reaches only J, not the residual), and the
    light state at u (where a finer model's render may start, resampled).  Without a Jacobian
    (the primal alone: shapes) the tangents are ``guess`` as given.

    The light solve itself starts from zero: started from the last step's light (a warm
    start) it took 10-11 GMRES steps instead of 14 (fog-balls, N = 28), but the images then
    carry the light's tolerance as noise that depends on the path (1e-5 relative), which
    near the optimum made the Levenberg–Marquardt trial points look worse than they were: 7
    steps, 3 of them rejected, against 5 (stop 60)."""

    @jax.custom_jvp
    def f(u, base, guess):
        y, code, state = problem.model(model, u, base)
        return y, code, guess, state

    @f.defjvp
    def _jvp(primals, tangents):
        (u_, base_, guess_), (t, _, _) = primals, tangents  # base and guess are data
        y, J, code, nxt, state = problem.jacobian_and_tangents(model, u_, base_, guess_)
        out = (y, code, nxt, state)
        return out, (J @ t, np.zeros(np.shape(code), jax.dtypes.float0),
                     *jax.tree.map(jnp.zeros_like, (nxt, state)))

    return f(u, base, guess)


def residual(problem: FitProblem, u, args):
    """(weighted, normalised, robustly rescaled residuals (P,), light result code, the model's
    images (P,) behind them, the light state's tangents at u: the next evaluation's guess,
    the light state at u).

    args = (model, (target, sqrt_w, scale, loss_scale, base, guess)): the images flattened
    over the cameras, the weights' square roots, the target's RMS, the robust loss's
    threshold, the parameters that are not fitted, and where the tangent solves start
    (:func:`tangent_start`, or an earlier evaluation's tangents)."""
    model, (target, sw, scale, c, base, guess) = args
    y, code, nxt, state = _model_cj(problem, model, u, base, guess)
    r = sw * (y - target) / scale
    if problem.loss != "linear":
        r = r * robust_factor((r / c) ** 2, problem.loss)
    return r, code, y, nxt, state


def residual_and_jacobian(problem: FitProblem, u, args):
    """Residual, its Jacobian and the model images at u (for the statistics)."""
    model, (target, sw, scale, c, base, guess) = args
    y, J, code = problem.model_and_jacobian(model, u, base, guess)
    r = sw * (y - target) / scale
    Jr = (sw / scale)[:, None] * J
    if problem.loss != "linear":
        f = robust_factor((r / c) ** 2, problem.loss)
        # d(r·f(r))/dr, by autodiff of the scalar map
        dfr = jax.vmap(jax.grad(lambda x: x * robust_factor((x / c) ** 2, problem.loss)))(r)
        Jr = dfr[:, None] * Jr
        r = r * f
    return r, Jr, y, code
