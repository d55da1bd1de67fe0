"""The whole pipeline: one solve for all cameras, images, and gradients of an image loss."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from difffog import Renderer, SweepSolver, get_param, load_scene, set_param


def _small_scene():
    scene = load_scene("fog-balls", ["shape.walls.thickness=0.1"])  # > one voxel at N = 12
    cams = tuple(dataclasses.replace(c, resolution=(12, 10)) for c in scene.cameras)
    return scene.replace(cameras=cams)


def test_render_returns_every_camera_with_schema_shapes():
    r = Renderer(_small_scene(), resolution=12, solver=SweepSolver(M=2, tol=1e-3), supersample=1)
    out = r.render()
    assert set(out.images) == {"top", "oblique"}
    for img in out.images.values():
        assert img.shape == (10, 12) and img.dtype == np.float32  # (height, width)
        assert np.all(np.isfinite(img)) and img.min() >= 0
    assert out.settings["resolution"] == 12
    assert out.timings["solve_s"] > 0 and out.timings["render_s"] > 0


PATHS = ["fog.scattering", "fog.absorption", "shape.walls.albedo", "shape.ball-mid.albedo",
         "sun.irradiance", "sky.radiance"]


@pytest.mark.slow  # one more FD check of the whole chain (sweep, camera, fit have theirs)
def test_image_loss_gradient_matches_finite_differences(x64):
    scene = _small_scene()
    solver = SweepSolver(M=2, max_iterations=1000, tol=1e-12, adjoint_rtol=1e-11)
    r = Renderer(scene, resolution=12, solver=solver, supersample=1)
    p0 = r.params(jnp.float64)
    target = jax.tree.map(lambda a: 0.9 * a, r(p0))

    def loss(p):
        imgs = r(p)
        return sum(jnp.sum((imgs[k] - target[k]) ** 2) for k in imgs)

    g = jax.jit(jax.grad(loss))(p0)
    f = jax.jit(loss)
    for path in PATHS:
        v = float(get_param(p0, scene, path))
        eps = 1e-5 * v
        fd = float(f(set_param(p0, scene, path, v + eps)) - f(set_param(p0, scene, path, v - eps)))
        fd /= 2 * eps
        assert float(get_param(g, scene, path)) == pytest.approx(fd, rel=1e-5), path
