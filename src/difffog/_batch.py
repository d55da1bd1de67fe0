"""Many parameter sets at once: ``vmap`` over a batch of ``Params``, sharded over devices.

A parameter sweep or a set of fits renders the same scene (one lattice, one compiled program)
for many parameter values.  ``stack_params`` makes one ``Params`` whose leaves carry a leading
batch axis; ``render_batch`` maps the renderer over it with ``vmap``, every device rendering its share
of the batch with its own iteration count, with no communication.  The results equal rendering
the parameter sets one by one.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ._errors import SolverError
from ._params import Params


def stack_params(params: Sequence[Params]) -> Params:
    """One ``Params`` whose leaves have a leading axis of ``len(params)``."""
    params = list(params)
    if not params:
        raise SolverError("stack_params: the list of parameter sets is empty")
    shapes = {jax.tree.structure(p) for p in params}
    if len(shapes) != 1:
        raise SolverError("stack_params: the parameter sets come from different scenes")
    return jax.tree.map(lambda *xs: jnp.stack(xs), *params)


def unstack_params(params: Params) -> list[Params]:
    """The inverse of :func:`stack_params`."""
    n = batch_size(params)
    return [jax.tree.map(lambda x: x[i], params) for i in range(n)]


def batch_size(params: Params) -> int:
    n = {int(x.shape[0]) if x.ndim else -1 for x in jax.tree.leaves(params)}
    if len(n) != 1 or -1 in n:
        raise SolverError(
            "a batch of parameters needs a leading batch axis on every leaf: build it with "
            "difffog.stack_params([params, ...])"
        )
    return n.pop()


def batch_devices(devices: int) -> list:
    """The first ``devices`` JAX devices, or a SolverError saying how to get them."""
    devs = jax.devices()
    if not isinstance(devices, (int, np.integer)) or devices < 1:
        raise SolverError(f"devices must be a positive integer, got {devices!r}")
    if len(devs) < devices:
        raise SolverError(
            f"devices={devices} needs {devices} JAX devices, found {len(devs)} "
            f"({devs[0].platform}); on a CPU set "
            f"XLA_FLAGS=--xla_force_host_platform_device_count={devices} before JAX is imported"
        )
    return devs[:devices]


@functools.lru_cache(maxsize=16)
def _jit_vmap(fn):
    """One compiled ``jit(vmap(fn))`` per function (bound methods compare by their object), so
    repeated batches of the same renderer or fit step do not compile again."""
    return jax.jit(jax.vmap(fn))


def map_batch(fn, batch, devices: int = 1):
    """``vmap(fn)(batch)`` (``batch``: any pytree of arrays with a leading batch axis) with the
    batch split over ``devices`` devices.

    Each device gets a contiguous share (a batch that does not divide is padded with copies of
    its last entry, and the results cropped) and runs one compiled ``jit(vmap(fn))`` on it;
    JAX dispatches the calls asynchronously, so the devices work at the same time, with no
    communication between them.  (This is plain data parallelism on purpose: under
    ``shard_map`` the vmapped GMRES light solve ran more than 20× slower on 2 CPU devices.)
    Returns arrays on the first device.  ``devices=1`` is ``jit(vmap(fn))``, differentiable.
    """
    n = batch_size(batch)
    jitted = _jit_vmap(fn)
    if devices == 1:
        return jitted(batch)
    devs = batch_devices(devices)
    per = -(-n // devices)
    extra = per * devices - n
    if extra:
        batch = jax.tree.map(
            lambda x: jnp.concatenate([x, jnp.repeat(x[-1:], extra, axis=0)]), batch)
    outs = [jitted(jax.device_put(jax.tree.map(lambda x: x[i * per:(i + 1) * per], batch), d))
            for i, d in enumerate(devs)]
    out = jax.tree.map(lambda *xs: jnp.concatenate([jax.device_put(x, devs[0]) for x in xs]),
                       *outs)
    return jax.tree.map(lambda x: x[:n], out) if extra else out


def render_batch(renderer, params: Params | Sequence[Params], *, devices: int = 1):
    """Images of every camera for every parameter set: ``{camera: (batch, H, W)}``.

    renderer: a ``Renderer`` (or any forward model with ``_forward_impl``-style ``__call__``);
    params: a list of ``Params`` or one stacked ``Params``; devices: how many JAX devices share
    the batch (each renders ``ceil(batch / devices)`` parameter sets).
    """
    if not isinstance(params, Params):
        params = stack_params(params)
    solver_devices = getattr(getattr(renderer, "solver", None), "devices", 1)
    if devices > 1 and solver_devices > 1:
        raise SolverError(
            f"render_batch(devices={devices}) with a solver that itself runs on "
            f"{solver_devices} devices: use one or the other"
        )
    fn = getattr(renderer, "_forward_impl", renderer)
    return map_batch(fn, params, devices)
