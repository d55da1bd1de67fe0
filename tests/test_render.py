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


def test_renders_repeat_bit_for_bit():
    """Deterministic: the same model renders the same images, bit for bit, each time (the
    native kernel shares its work between the CPU's cores in a fixed split; a reduction whose
    order followed the threads' timing would not be).  The gradient: the slow test below."""
    import numpy as np

    m = build_model("sweep", small_scene())
    out = df.render(m)
    first = {k: np.asarray(v) for k, v in out.images.items()}
    again = {k: np.asarray(v) for k, v in df.render(m).images.items()}
    assert first.keys() == again.keys() and all(
        np.array_equal(first[k], again[k]) for k in first)
    assert all(np.all(v > 0) for v in first.values())  # a lit scene, not two blank images
    # the cameras in one march on a CPU (half the compile of a march per core), one each on a
    # GPU (one lane's images equal the lanes': test_camera.py's
    # test_cameras_marched_together_equal_each_alone)
    cpu = jax.default_backend() == "cpu"
    assert len(m.cameras) == 2 and out.settings["march_lanes"] == (1 if cpu else 2)


# slow since stop 80 (the default suite's 12-minute budget on 2 cores: ~25 s there, the
# gradient's programs to compile)
@pytest.mark.slow
def test_gradients_repeat_bit_for_bit():
    """The loss gradient of the same model is the same, bit for bit, each time (the adjoint's
    transposed sweeps share the cores in the same fixed split)."""
    import numpy as np

    m = build_model("sweep", small_scene())
    p = m.params()

    def loss(q):
        return sum(jnp.sum(v * v) for v in m(q).values())

    g1, g2 = jax.grad(loss)(p), jax.grad(loss)(p)
    leaves1, leaves2 = jax.tree.leaves(g1), jax.tree.leaves(g2)
    assert all(np.array_equal(np.asarray(a), np.asarray(b)) for a, b in zip(leaves1, leaves2))
    assert float(df.get_param(g1, m.scene, "fog.scattering")) != 0.0


def test_the_vacuum_margin_changes_no_image(monkeypatch):
    """Light that leaves the (convex) domain never comes back, so the lattice's vacuum margin
    only serves what lies on the domain's boundary (the walls' outer faces and tops): the
    default two nodes render fog-balls as M + 1 (the margin until stop 82) does, to float32
    rounding, on a lattice 2·(M − 1) nodes narrower."""
    import numpy as np

    from difffog.forward.sweep import _model

    scene = small_scene()
    M = 2  # (the model of the test above: its programs are compiled already)
    small, default = build_model("sweep", scene, M=M), _model.VACUUM_MARGIN
    monkeypatch.setattr(_model, "VACUUM_MARGIN", M + 1)
    wide = build_model("sweep", scene, M=M)
    assert [n - 2 * (M + 1 - default) for n in wide.lattice.shape] == list(small.lattice.shape)
    a, b = df.render(small).images, df.render(wide).images
    for k in a:
        assert float(np.mean(a[k])) > 0.01
        np.testing.assert_allclose(np.asarray(a[k]), np.asarray(b[k]), rtol=2e-5,
                                   atol=2e-6 * float(np.mean(b[k])))
