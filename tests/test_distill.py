"""`dano.fields.distill`: a neural field regressed onto another field's densities."""

import jax
import jax.numpy as jnp
import numpy as np

from dano.fields import NeuralField, NeuralFieldConfig, SphereField, distill


def test_distill_fits_a_sphere_and_is_deterministic():
    teacher = SphereField(radius=0.05)
    config = NeuralFieldConfig(depth=2, width=32, n_frequencies=2)
    student = NeuralField(teacher.bounds, config, key=jax.random.key(0))
    x = jnp.asarray(np.random.default_rng(0).uniform(np.asarray(teacher.bounds[0]), np.asarray(teacher.bounds[1]),
                                                     size=(2000, 3)))  # fmt: skip
    peak = float(jnp.max(teacher(x)))

    def error(field):
        return float(jnp.sqrt(jnp.mean((field(x) - teacher(x)) ** 2)) / peak)

    fitted = distill(student, teacher, steps=300, batch=1024, learning_rate=3e-3, key=jax.random.key(1),
                     progress=False)  # fmt: skip
    assert error(fitted) < 0.5 * error(student)  # the regression fits (relative RMS error at least halved)
    inside, outside = fitted(jnp.zeros((1, 3))), fitted(jnp.full((1, 3), 0.09))
    assert float(inside[0]) > 0.5 * peak > float(outside[0])
    again = distill(student, teacher, steps=300, batch=1024, learning_rate=3e-3, key=jax.random.key(1),
                    progress=False)  # fmt: skip
    np.testing.assert_array_equal(np.asarray(again(x)), np.asarray(fitted(x)))  # the same key, the same field
