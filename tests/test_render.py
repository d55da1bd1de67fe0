"""The whole pipeline's gradient: one light solve for all cameras, images, and the gradient of
an image loss against finite differences over every kind of parameter.

(Images, ``df.render``, its timings and result, and a three-parameter gradient check of both
forward models are in test_interface.py.)
"""

import jax
import jax.numpy as jnp
import pytest

import difffog as df
from helpers import build_model, image_loss_gradient_matches_fd, small_scene

PATHS = ["fog.scattering", "fog.absorption", "shape.walls.albedo", "shape.ball-mid.albedo",
         "sun.irradiance", "sky.radiance"]


@pytest.mark.slow  # one more FD check of the whole chain (sweep, camera, fit have theirs)
def test_image_loss_gradient_matches_finite_differences(x64):
    scene = small_scene()
    m = build_model("sweep", scene, max_iterations=1000, tol=1e-12, adjoint_rtol=1e-11)
    p0 = m.params(jnp.float64)
    light = jax.jit(lambda m, p: m.light(p))(m, p0)
    assert int(light.result) == df.RESULTS.successful
    image_loss_gradient_matches_fd(m, scene, PATHS)  # m(p) raises if a light solve failed
