"""A fit's checkpoint: the optimizer's state after every step, written atomically, so that a
killed fit resumes (``resume=True``, ``difffog fit --resume``) and reaches the same answer as
an uninterrupted one.  A fingerprint of the scene, targets, unknowns and settings guards
against resuming a different fit."""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._errors import DifffogError


def fingerprint(**kw) -> str:
    return hashlib.sha256(json.dumps(kw, sort_keys=True, default=str).encode()).hexdigest()[:16]


def save_checkpoint(path: Path, u, state, k: int, history: list, fingerprint: str,
                     elapsed: float) -> None:
    leaves = jax.tree.leaves(eqx.filter((u, state), eqx.is_array))
    meta = json.dumps({"fingerprint": fingerprint, "step": k, "history": history,
                       "elapsed_s": elapsed})
    savez_atomic(path, meta=np.array(meta),
                 **{f"leaf{i}": np.asarray(x) for i, x in enumerate(leaves)})


def savez_atomic(path: Path, **arrays) -> None:
    """``np.savez(path, **arrays)`` written to a temporary file beside it and moved into place:
    a kill leaves the previous checkpoint intact."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".ckpt-", suffix=".npz", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez(f, **arrays)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def load_checkpoint(path: Path, u0, state0, fingerprint: str):
    if not path.exists():
        raise DifffogError(f"resume: no checkpoint at {path}; run the fit without resume first")
    with np.load(path, allow_pickle=False) as z:
        meta = json.loads(str(z["meta"]))
        if meta["fingerprint"] != fingerprint:
            raise DifffogError(
                f"resume: the checkpoint {path} belongs to a different fit (scene, targets, "
                f"unknowns or settings changed); delete it or run without resume")
        dyn, static = eqx.partition((u0, state0), eqx.is_array)
        old = jax.tree.leaves(dyn)
        stored = sum(1 for k in z.files if k.startswith("leaf"))
        # (a checkpoint of an older difffog: the state has gained leaves since, e.g. the
        # light state and its tangents in the optimizer's aux at stop 61)
        new = ([z[f"leaf{i}"] for i in range(len(old))] if stored == len(old) else None)
    if new is None or any(a.shape != b.shape or np.dtype(a.dtype) != b.dtype
                          for a, b in zip(old, new)):
        raise DifffogError(f"resume: the checkpoint {path} does not match this fit's "
                           f"solver state (written by another difffog version?); delete it "
                           f"or run without resume")
    dyn = jax.tree.unflatten(jax.tree.structure(dyn), [jnp.asarray(b) for b in new])
    u, state = eqx.combine(dyn, static)
    return u, state, meta["step"], meta["history"], meta["elapsed_s"]


def digest(a: np.ndarray) -> str:
    """A short hash of an array's bytes (targets and weights in the fingerprint)."""
    return hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()
