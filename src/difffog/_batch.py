"""Many parameter sets at once: ``vmap`` over a batch of ``Params``, sharded over devices.

A parameter sweep or a set of fits renders the same scene (one lattice, one compiled program)
for many parameter values.  ``stack_params`` makes one ``Params`` whose leaves carry a leading
batch axis; ``render_batch`` maps the renderer over it with ``vmap`` inside a ``shard_map`` over
a 1-D ("batch") device mesh: every device renders its share of the batch with its own
iteration count, with no communication.  The results equal rendering the parameter sets one
by one.
"""

from __future__ import annotations

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


def batch_mesh(devices: int) -> jax.sharding.Mesh:
    devs = jax.devices()
    if devices < 1:
        raise SolverError(f"devices must be >= 1, got {devices}")
    if len(devs) < devices:
        raise SolverError(
            f"devices={devices} needs {devices} JAX devices, found {len(devs)} "
            f"({devs[0].platform}); on a CPU set "
            f"XLA_FLAGS=--xla_force_host_platform_device_count={devices} before JAX is imported"
        )
    return jax.sharding.Mesh(np.array(devs[:devices]), ("batch",))


def map_batch(fn, params: Params, devices: int = 1):
    """``vmap(fn)(params)`` with the batch split over ``devices`` devices (``shard_map``).

    A batch that does not divide evenly is padded with copies of its last entry, and the
    results cropped.  Differentiable.
    """
    n = batch_size(params)
    if devices == 1:
        return jax.vmap(fn)(params)
    extra = -n % devices
    if extra:
        params = jax.tree.map(
            lambda x: jnp.concatenate([x, jnp.repeat(x[-1:], extra, axis=0)]), params)
    spec = jax.sharding.PartitionSpec("batch")
    out = jax.shard_map(jax.vmap(fn), mesh=batch_mesh(devices), in_specs=spec, out_specs=spec,
                        check_vma=False)(params)
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
    return jax.jit(lambda p: map_batch(fn, p, devices))(params)
