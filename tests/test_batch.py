"""Batches of parameter sets: vmap over Params, sharded over devices."""

import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import difffog as df


@pytest.fixture(scope="module")
def renderer():
    scene = df.load_scene("fog-balls", ["shape.walls.thickness=0.1"])
    return df.Renderer(scene, resolution=12, solver=df.SweepSolver(M=2, tol=1e-6),
                       supersample=1)


def _sets(r):
    p0 = r.params()
    return [df.set_param(df.set_param(p0, r.scene, "fog.scattering", z), r.scene,
                         "shape.walls.albedo", a) for z, a in ((0.5, 0.2), (2.0, 0.5), (4.0, 0.9))]


def test_batch_equals_one_by_one(renderer):
    sets = _sets(renderer)
    batch = df.render_batch(renderer, sets)
    for i, p in enumerate(sets):
        one = renderer(p)
        for cam, img in one.items():
            np.testing.assert_allclose(np.asarray(batch[cam][i]), np.asarray(img),
                                       rtol=1e-5, atol=1e-7 * float(img.max()))
    # the batch really varies: more scattering, different images
    assert float(jnp.abs(batch["top"][0] - batch["top"][2]).max()) > 0.05 * float(
        batch["top"].max())


def test_stack_and_unstack_round_trip(renderer):
    sets = _sets(renderer)
    back = df.unstack_params(df.stack_params(sets))
    for a, b in zip(sets, back):
        for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_batch_errors(renderer):
    with pytest.raises(df.SolverError, match="empty"):
        df.stack_params([])
    with pytest.raises(df.SolverError, match="stack_params"):
        df.render_batch(renderer, renderer.params())  # not stacked
    with pytest.raises(df.SolverError, match="xla_force_host_platform_device_count"):
        df.render_batch(renderer, _sets(renderer), devices=len(jax.devices()) + 1)


def test_batch_over_two_devices_matches_one():
    """3 parameter sets over 2 host devices (padded to 4) give the one-device images."""
    code = """
import jax, numpy as np, difffog as df
scene = df.load_scene("fog-balls", ["shape.walls.thickness=0.1"])
r = df.Renderer(scene, resolution=12, solver=df.SweepSolver(M=2, tol=1e-6), supersample=1)
p0 = r.params()
sets = [df.set_param(p0, scene, "fog.scattering", z) for z in (0.5, 2.0, 4.0)]
a = df.render_batch(r, sets, devices=1)
b = df.render_batch(r, sets, devices=2)
for k in a:
    assert a[k].shape == b[k].shape == (3,) + a[k].shape[1:], (a[k].shape, b[k].shape)
    err = float(np.max(np.abs(np.asarray(a[k]) - np.asarray(b[k]))) / np.max(np.asarray(a[k])))
    assert err <= 1e-6, (k, err)
print("ok")
"""
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0 and r.stdout.strip().endswith("ok"), r.stderr[-2000:]


def test_cli_render_devices_gives_the_same_images(tmp_path):
    """`difffog render --devices 2` (two host devices, asked for by the CLI itself) writes the
    images of one device, to the solve's tolerance (GMRES on a mesh also sweeps the Λ off the
    fog that one device skips, so its iterates differ in the last digits; the fixed point is
    the same)."""
    src = os.path.join(os.path.dirname(__file__), "..", "src")
    env = dict(os.environ, PYTHONPATH=os.path.abspath(src) + os.pathsep
               + os.environ.get("PYTHONPATH", ""))
    env.pop("XLA_FLAGS", None)
    for n in (1, 2):
        r = subprocess.run([sys.executable, "-m", "difffog", "render", "fog-balls", "-N", "12",
                            "-M", "2", "--set", "shape.walls.thickness=0.1", "--tol", "1e-6",
                            "--camera", "top", "--supersample", "1", "--devices", str(n), "-q",
                            "--out", str(tmp_path / f"d{n}")], env=env, capture_output=True,
                           text=True, timeout=600)
        assert r.returncode == 0, r.stderr[-2000:]
    a, b = (np.load(tmp_path / f"d{n}" / "top.npy") for n in (1, 2))
    assert a.max() > 0 and np.max(np.abs(a - b)) <= 1e-5 * a.max()


@pytest.mark.slow
def test_fit_batch_over_two_devices_matches_one():
    """fit_batch with the fits split over 2 host devices gives the one-device estimates."""
    code = """
import numpy as np, difffog as df
from difffog._fit import make_forward
sc = df.load_scene("fog-balls", ["shape.walls.thickness=0.1"])
fwd = make_forward(sc, "sweep", cameras=["top"], resolution=12, directions=2, downsample=8)
ts = [{k: np.asarray(v) for k, v in fwd(df.set_param(fwd.params(), fwd.scene,
                                                      "fog.scattering", z)).items()}
      for z in (1.5, 2.0, 3.0)]
unk = {"fog.scattering": 1.2, "fog.absorption": 0.8}
a = df.fit_batch(sc, ts, unk, forward=fwd, devices=1)
b = df.fit_batch(sc, ts, unk, forward=fwd, devices=2)
for ra, rb, z in zip(a, b, (1.5, 2.0, 3.0)):
    assert ra.converged and rb.converged and ra.iterations == rb.iterations
    for p in unk:
        assert abs(ra.estimates[p] / rb.estimates[p] - 1) <= 1e-6, (p, ra.estimates, rb.estimates)
    assert abs(rb.estimates["fog.scattering"] / z - 1) <= 1e-3
print("ok")
"""
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                       timeout=900)
    assert r.returncode == 0 and r.stdout.strip().endswith("ok"), r.stderr[-2000:]
