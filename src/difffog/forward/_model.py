"""One interface for both forward models: parameters → light → images of every camera.

A forward model is an :class:`equinox.Module` that holds a scene, its cameras and everything
the host prepared once (the lattice's static structure, the splat's sheets: arrays, so they
are pytree leaves and pass through ``jit`` as arguments rather than constants).  Its methods
are pure JAX functions of the parameters:

    light = model.light(params)                # AbstractLight: the light, with a result code
    images = model.images_from(light, params)  # {camera: (H, W)}
    images = model.images(params)              # both, raising if the light solve failed
    images = model(params)                     # the same, jitted

so they jit, vmap and differentiate.  The sweep (``sweep/``) and the splat (``splat/``) are
the two final subclasses; :func:`difffog.forward_model` builds either by name.  The same
:func:`render`, :func:`render_batch`, fit and benchmarks serve both.
"""

from __future__ import annotations

import abc
import time
import warnings
from dataclasses import dataclass, field

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from .._errors import SolverError, ThickStepWarning, ThinLayerWarning
from .._results import RESULTS, check, error_if_failed
from ..scene._description import Camera, Scene
from ..scene._params import _SCALAR_PATHS, Params


class AbstractLight(eqx.Module):
    """The light a forward model computed for one parameter set.

    result: a :class:`difffog.RESULTS` code (int32): did the light solve converge?
    iterations: iterations of the light solve (1 for a single pass).
    error_estimate: its estimated remaining relative error (0 for a direct method).
    """

    result: eqx.AbstractVar[Int[Array, ""]]
    iterations: eqx.AbstractVar[Int[Array, ""]]
    error_estimate: eqx.AbstractVar[Float[Array, ""]]

    @abc.abstractmethod
    def fluence_at(self, points: Float[Array, "... 3"]) -> Float[Array, "..."]:
        """The light at world points (..., 3): the total fluence, i.e. radiance integrated
        over all directions (collided and uncollided), in units of the sun's irradiance."""

    @abc.abstractmethod
    def report(self) -> dict:
        """A JSON-able summary for reports (host side, concrete values)."""


class HostInfo:
    """Host-side facts a model keeps for reports (timings, the lattice, pass summaries) in a
    static field, never traced.  Any two compare equal and hash alike: what a model computes
    lives in its arrays and its other static fields, so two models built alike (the same
    scene at the same settings, a fit level rebuilt with a new start) share their compiled
    programs instead of compiling again (by identity, every build compiled anew)."""

    def __init__(self, **items):
        self.__dict__.update(items)

    def __eq__(self, other):
        return isinstance(other, HostInfo)

    def __hash__(self):
        return hash(HostInfo)

    def __repr__(self):
        return f"HostInfo({', '.join(self.__dict__)})"


class AbstractForwardModel(eqx.Module):
    """Parameters → images of the scene's cameras.  Subclasses are final.

    scene: the scene description (static).
    cameras: the cameras this model renders (static; a subset of the scene's, possibly at a
        reduced resolution).
    """

    scene: eqx.AbstractVar[Scene]
    cameras: eqx.AbstractVar[tuple[Camera, ...]]

    # -- what each model provides --------------------------------------------------------
    @abc.abstractmethod
    def light(self, params: Params) -> AbstractLight:
        """The light for these parameters (differentiable), with its result code."""

    @abc.abstractmethod
    def images_from(self, light: AbstractLight, params: Params) -> dict[str, Float[Array, "H W"]]:
        """Every camera's (H, W) image (linear radiance, row 0 at the top) from ``light``."""

    @abc.abstractmethod
    def check(self, params: Params) -> None:
        """Host-side check of concrete parameters: a one-line error for values this model
        cannot take (e.g. a term the sweep dropped), before anything is compiled."""

    @abc.abstractmethod
    def settings(self) -> dict:
        """The model's settings and sizes, JSON-able (``report.json``, benchmarks)."""

    def step_warning(self, params: Params) -> str | None:
        """A one-line warning when these concrete parameters make the model's discretization
        optically coarse (``ThickStepWarning``), else None.  Default: none."""
        return None

    def layer_warning(self, params: Params) -> str | None:
        """A one-line warning when the fog is a thin layer the model's directions resolve
        poorly (``ThinLayerWarning``), else None.  Default: none."""
        return None

    def edge_pixels(self) -> dict[str, np.ndarray] | None:
        """{camera: (H, W) bool} the pixels whose footprint straddles a geometric or a shadow
        edge, known from the exact geometry (host, no light solve), or None where this model
        does not know them.  A fit down-weights them (``fit(edge_weight=...)``).  Default:
        None."""
        return None

    def zero_light_state(self, dtype):
        """A light state of zeros (the shape of ``light.state``) for a model whose ``light``
        takes ``init`` (a warm start, see ``SweepModel.light``), else None.  Default: None."""
        return None

    # -- the same for every model ---------------------------------------------------------
    def params(self, dtype=None) -> Params:
        """The scene's parameters as a pytree (float32 unless x64 is on or ``dtype`` given)."""
        return Params.from_scene(self.scene, dtype)

    def images(self, params: Params | None = None, *, throw: bool = True):
        """{camera: (H, W) image}: pure, jit-, vmap- and grad-able.  With ``throw`` a failed
        light solve raises at run time (``equinox`` runtime error naming the failure);
        ``throw=False`` returns the images whatever the result (see :meth:`light`)."""
        params = self.params() if params is None else params
        light = self.light(params)
        imgs = self.images_from(light, params)
        return error_if_failed(imgs, light.result) if throw else imgs

    def __call__(self, params: Params | None = None, *, throw: bool = True):
        """:meth:`images`, jitted (the model's arrays are arguments, not constants)."""
        params = self.params() if params is None else params
        return images_jit(self, params, throw)


def select_cameras(scene: Scene, cameras=None) -> tuple[Camera, ...]:
    """The cameras a model renders: all of the scene's (None), or those named (or given as
    :class:`Camera` objects, e.g. at a reduced resolution)."""
    if cameras is None:
        return tuple(scene.cameras)
    if isinstance(cameras, (str, Camera)):
        cameras = [cameras]
    return tuple(c if isinstance(c, Camera) else scene.camera(c) for c in cameras)


@eqx.filter_jit
def images_jit(model, params, throw):
    return model.images(params, throw=throw)


@eqx.filter_jit
def light_jit(model, params):
    return model.light(params)


@eqx.filter_jit
def images_from_jit(model, light, params):
    return model.images_from(light, params)


# ------------------------------------------------------------------------------------------
# render: the timed, checked one-call path
# ------------------------------------------------------------------------------------------
@dataclass
class Rendered:
    """What :func:`render` returns.

    images: {camera: (H, W) float32 NumPy image}, linear radiance, row 0 at the top.
    light: the model's :class:`AbstractLight` (the sweep's :class:`LightField`, the splat's
        sheet light).
    result: the light solve's :class:`difffog.RESULTS` member.
    timings: seconds per stage (set-up, compile and run of the light and of the images).
    settings: the model's settings (JSON-able).
    """

    images: dict[str, np.ndarray]
    light: AbstractLight
    result: RESULTS = RESULTS.successful
    timings: dict[str, float] = field(default_factory=dict)
    settings: dict = field(default_factory=dict)

    @property
    def converged(self) -> bool:
        return self.result == RESULTS.successful


def failure_details(light: AbstractLight, params: Params | None = None) -> str:
    """'estimated error 0.3 after 500 iterations' for a concrete light (with the largest
    inputs, :func:`largest_inputs`, when the light is not finite and ``params`` are given)."""
    text = (f"estimated error {float(light.error_estimate):.3g} after "
            f"{int(light.iterations)} iterations")
    if params is not None and int(light.result) == RESULTS.nonfinite:
        text += f"; the largest inputs: {largest_inputs(params)}"
    return text


def largest_inputs(params: Params, k: int = 3) -> str:
    """The ``k`` parameters of largest magnitude, named as a scene file names them
    ('fog.scattering = 1e+14, sun.irradiance = 3'): where a valid input overflowed, the
    message says which input led there."""
    vals = [(path, float(np.asarray(getattr(params, name))))
            for path, name in _SCALAR_PATHS.items()]
    for name in ("albedo", "emission"):
        a = np.asarray(getattr(params, name), np.float64).reshape(-1)
        if a.size:
            i = int(np.argmax(np.abs(a)))
            vals.append((f"shape #{i} {name}", float(a[i])))
    vals.sort(key=lambda t: -abs(t[1]) if np.isfinite(t[1]) else -np.inf)
    return ", ".join(f"{p} = {v:.3g}" for p, v in vals[:k])


#: the share of its peak by which a light solve's fixed point may dip below 0 (clipped) before
#: :func:`render` warns (GMRES's own residual stays near its tol, 1e-4 by default)
DIP_WARNING = 0.01


def dip_warning(light) -> str | None:
    """A one-line warning when the light's fixed point dipped below 0 by more than
    ``DIP_WARNING`` of its peak (``LightField.dip``), else None."""
    dip = getattr(light, "dip", None)
    if dip is None or not float(dip) > DIP_WARNING:
        return None
    return (f"the light solve's fixed point dipped below 0 (down to −{float(dip):.1%} of its "
            f"peak fluence) and was clipped to 0: the linear scheme does that where one "
            f"lattice step spans many mean free paths; a finer resolution (or scheme='step', "
            f"--scheme step) avoids it")


def render(model, params: Params | None = None, *, throw: bool = True, **build) -> Rendered:
    """Render every camera of a forward model (or of a scene) once, timing each stage.

    model: a forward model, or a :class:`difffog.Scene` (then ``build`` holds
        :func:`difffog.forward_model`'s arguments: ``solver``, ``accuracy``, ``cameras``,
        settings such as ``resolution``).
    params: the parameters (default: the scene's).
    throw: raise a one-line :class:`SolverError` if the light solve did not converge
        (naming its estimated error and iterations); False returns the result in
        ``Rendered.result`` instead.
    Compilation is timed apart from the run (``*_compile_s``); non-finite images raise.
    """
    if isinstance(model, Scene):
        from ._registry import forward_model

        model = forward_model(model, **build)
    elif build:
        raise SolverError(f"render: {', '.join(sorted(build))} only apply when rendering a "
                          "scene; the forward model given is already built")
    if not isinstance(model, AbstractForwardModel):
        raise SolverError(f"render: expected a forward model or a Scene, got "
                          f"{type(model).__name__}")
    params = model.params() if params is None else params
    model.check(params)
    warn_thick_steps(model, params, stacklevel=3)
    if layer := model.layer_warning(params):
        warnings.warn(layer, ThinLayerWarning, stacklevel=2)
    timings = dict(model.settings().get("setup_s", {}))
    t = time.perf_counter()
    light_fn = light_jit.lower(model, params).compile()
    timings["light_compile_s"] = time.perf_counter() - t
    t = time.perf_counter()
    light = jax.block_until_ready(light_fn(model, params))
    timings["light_s"] = time.perf_counter() - t
    progress = getattr(getattr(model, "solver", None), "progress", None)
    if progress is not None:
        progress.close()
    t = time.perf_counter()
    img_fn = images_from_jit.lower(model, light, params).compile()
    timings["images_compile_s"] = time.perf_counter() - t
    t = time.perf_counter()
    imgs = jax.block_until_ready(img_fn(model, light, params))
    timings["images_s"] = time.perf_counter() - t
    result = RESULTS(int(light.result))
    if throw:
        check(light.result, "render", failure_details(light, params))
    if result == RESULTS.successful and (dip := dip_warning(light)) is not None:
        # (an unconverged iterate's dip says nothing more than its result code)
        warnings.warn(dip, ThickStepWarning, stacklevel=2)
    images = {k: np.asarray(v, np.float32) for k, v in imgs.items()}
    if result == RESULTS.successful:
        for k, v in images.items():
            if not np.all(np.isfinite(v)):
                raise SolverError(f"camera '{k}': the image has non-finite values although the "
                                  f"light solve converged; the largest inputs: "
                                  f"{largest_inputs(params)} (if they are legitimate, use "
                                  f"float64: jax_enable_x64; otherwise please report the scene "
                                  f"and settings)")
    return Rendered(images=images, light=light, result=result, timings=timings,
                    settings=model.settings())


# ------------------------------------------------------------------------------------------
# many parameter sets at once
# ------------------------------------------------------------------------------------------
def warn_thick_steps(model: AbstractForwardModel, params: Params, stacklevel: int = 2) -> None:
    """Warn (``ThickStepWarning``) when ``model.step_warning(params)`` has something to say."""
    msg = model.step_warning(params)
    if msg:
        warnings.warn(msg, ThickStepWarning, stacklevel=stacklevel + 1)


def stack_params(params) -> Params:
    """One ``Params`` whose leaves have a leading axis of ``len(params)``."""
    params = list(params)
    if not params:
        raise SolverError("stack_params: the list of parameter sets is empty")
    if len({jax.tree.structure(p) for p in params}) != 1:
        raise SolverError("stack_params: the parameter sets come from different scenes")
    return jax.tree.map(lambda *xs: jnp.stack(xs), *params)


def unstack_params(params: Params) -> list[Params]:
    """The inverse of :func:`stack_params`."""
    n = batch_size(params)
    return [jax.tree.map(lambda x: x[i], params) for i in range(n)]


def batch_size(batch) -> int:
    n = {int(x.shape[0]) if x.ndim else -1 for x in jax.tree.leaves(batch)}
    if len(n) != 1 or -1 in n:
        raise SolverError("a batch needs a leading batch axis on every leaf: build a batch of "
                          "parameters with difffog.stack_params([params, ...])")
    return n.pop()


def batch_devices(devices: int) -> list:
    """The first ``devices`` JAX devices, or a one-line error saying how to get them."""
    if isinstance(devices, bool) or not isinstance(devices, (int, np.integer)) or devices < 1:
        raise SolverError(f"devices must be a positive integer, got {devices!r}")
    devs = jax.devices()
    if len(devs) < devices:
        raise SolverError(
            f"devices={devices} needs {devices} JAX devices, found {len(devs)} "
            f"({devs[0].platform}); on a CPU set "
            f"XLA_FLAGS=--xla_force_host_platform_device_count={devices} before JAX is imported")
    return devs[:devices]


@eqx.filter_jit
def _vmapped(fn, shared, batch):
    return eqx.filter_vmap(fn, in_axes=(None, 0))(shared, batch)


def map_batch(fn, shared, batch, devices: int = 1):
    """``vmap(fn, in_axes=(None, 0))(shared, batch)``, jitted, with the batch split over
    ``devices`` JAX devices.

    fn: a function of (shared, one batch entry); shared: a pytree every entry uses (a model:
        its arrays are arguments, not constants); batch: a pytree with a leading batch axis.
    Each device gets a contiguous share (a batch that does not divide is padded with copies of
    its last entry, and the results cropped) and runs the same compiled program; JAX
    dispatches the calls asynchronously, so the devices work at once, with no communication.
    (Plain data parallelism: each device runs the batched program on its share, with no
    communication.)  Returns arrays on the first device.
    """
    n = batch_size(batch)
    if devices == 1:
        return _vmapped(fn, shared, batch)
    devs = batch_devices(devices)
    per = -(-n // devices)
    extra = per * devices - n
    if extra:
        batch = jax.tree.map(lambda x: jnp.concatenate([x, jnp.repeat(x[-1:], extra, axis=0)]),
                             batch)
    outs = []
    for i, d in enumerate(devs):
        share = jax.tree.map(lambda x: x[i * per:(i + 1) * per], batch)
        outs.append(_vmapped(fn, jax.device_put(shared, d), jax.device_put(share, d)))
    out = jax.tree.map(lambda *xs: jnp.concatenate([jax.device_put(x, devs[0]) for x in xs]),
                       *outs)
    return jax.tree.map(lambda x: x[:n], out) if extra else out


def _images_unchecked(model, params):
    light = model.light(params)
    return model.images_from(light, params), light.result


def render_batch(model: AbstractForwardModel, params, *, devices: int = 1,
                 throw: bool = True) -> dict[str, Array]:
    """Images of every camera for every parameter set: ``{camera: (batch, H, W)}``.

    model: a forward model (sweep or splat).
    params: a list of ``Params`` or one stacked ``Params`` (:func:`stack_params`).
    devices: JAX devices that share the batch (each renders ``ceil(batch / devices)`` sets).
    throw: raise a one-line :class:`SolverError` naming the failed entries if any light solve
        did not converge; False returns the images regardless.
    """
    if not isinstance(model, AbstractForwardModel):
        raise SolverError(f"render_batch: expected a forward model (difffog.forward_model(...)),"
                          f" got {type(model).__name__}")
    if not isinstance(params, Params):
        params = stack_params(params)
    solver_devices = getattr(getattr(model, "solver", None), "devices", 1)
    if devices > 1 and solver_devices > 1:
        raise SolverError(f"render_batch(devices={devices}) with a solver that itself runs on "
                          f"{solver_devices} devices: use one or the other")
    images, results = map_batch(_images_unchecked, model, params, devices)
    if throw:
        bad = np.flatnonzero(np.asarray(results) != RESULTS.successful)
        if bad.size:
            first = RESULTS(int(np.asarray(results)[bad[0]]))
            raise SolverError(f"render_batch: the light solve of parameter set(s) "
                              f"{', '.join(map(str, bad[:10]))} failed ({first.name}): "
                              f"{first.message}")
    return images
