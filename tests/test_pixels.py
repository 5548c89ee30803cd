"""Identification from masks (`dano.vision.pixels`): the pixel loss of a simulated trajectory."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dano.build import build_dano
from dano.contact.wrench import ContactParams
from dano.fields import BoxField
from dano.sim import DanoBody, Scene
from dano.sysid.data import Track
from dano.sysid.problem import residuals
from dano.vision import camera_from_fov, look_at
from dano.vision.pixels import MaskConfig, MaskError, MaskTargets, mask_problem, simulated_silhouettes

SIZE = (0.09, 0.06, 0.03)
FPS = 120.0


def _scene(mu: float) -> Scene:
    obj = build_dano(BoxField(SIZE), n_points=200, mass=0.1)
    body = DanoBody("soap", obj, pos=(0.0, 0.0, SIZE[2] / 2), vel=(1.0, 0.2, 0.0), angvel=(0.0, 0.0, 2.0))
    return Scene(timestep=1 / FPS, substeps=4, bodies=(body,), contact=ContactParams(sliding_friction=mu))


def _problem(mu_data: float, frames: int = 6):
    """Masks rendered by the silhouette renderer itself from a simulated slide at `mu_data`."""
    camera = camera_from_fov(32, 24, np.radians(50.0), look_at([0.03, -0.15, 0.2], [0.03, 0.0, 0.0]))
    scene = _scene(0.3)
    t = np.arange(frames) / FPS
    pos = np.stack([1.0 * t, 0.2 * t, np.full(frames, SIZE[2] / 2)], axis=1)
    yaw = 2.0 * t
    quat = np.stack([np.cos(yaw / 2), 0 * t, 0 * t, np.sin(yaw / 2)], axis=1)
    start = Track(t=t, pos=pos, quat=quat)
    masks = np.zeros((frames, 24, 32))
    masks[:, 8:16, 10:22] = 1.0  # replaced below by the rendered truth
    config = MaskConfig(n_samples=24, first_frames=4)
    problem = mask_problem(scene, masks, camera, FPS, ["friction"], start=start, field=BoxField(SIZE), config=config)
    opacity, _ = simulated_silhouettes(problem, jnp.asarray([mu_data]), jnp.zeros((1, problem.n_state)))
    observed = problem.windows.observed
    assert isinstance(observed, MaskTargets)
    truth = MaskTargets(observed.origins, observed.directions, observed.uv, jnp.asarray(opacity)[None])
    windows = dataclasses.replace(problem.windows, observed=truth)
    return problem, windows


def test_pixel_loss_gradient_matches_central_differences():
    problem, windows = _problem(0.5)

    def loss(theta, delta):
        r = residuals(problem, theta, delta, windows)
        return 0.5 * jnp.sum(r * r)

    theta = jnp.asarray([0.35])
    delta = jnp.full((1, problem.n_state), 0.0).at[0, 3].set(0.05)  # a velocity correction
    g_theta, g_delta = jax.grad(loss, argnums=(0, 1))(theta, delta)
    h = 1e-6
    fd_theta = (loss(theta + h, delta) - loss(theta - h, delta)) / (2 * h)
    e = jnp.zeros_like(delta).at[0, 3].set(h)
    fd_vel = (loss(theta, delta + e) - loss(theta, delta - e)) / (2 * h)
    assert abs(float(fd_theta)) > 1e-3 and abs(float(fd_vel)) > 1e-3
    np.testing.assert_allclose(float(g_theta[0]), float(fd_theta), rtol=1e-4)
    np.testing.assert_allclose(float(g_delta[0, 3]), float(fd_vel), rtol=1e-4)


def test_the_loss_is_least_at_the_friction_that_made_the_masks():
    problem, windows = _problem(0.5, frames=10)

    def loss(mu):
        r = residuals(problem, jnp.asarray([mu]), jnp.zeros((1, problem.n_state)), windows)
        return float(0.5 * jnp.sum(r * r))

    values = [loss(mu) for mu in (0.3, 0.5, 0.7)]
    assert values[1] < 1e-12 < min(values[0], values[2])


def test_masks_that_cannot_be_fitted_are_refused():
    camera = camera_from_fov(32, 24, np.radians(50.0), look_at([0.0, -0.15, 0.2], [0.0, 0.0, 0.0]))
    scene = _scene(0.3)
    with pytest.raises(MaskError, match=r"\(24, 32\)"):
        mask_problem(scene, np.ones((5, 10, 10)), camera, FPS, ["friction"])
    with pytest.raises(MaskError, match="first mask is empty"):
        mask_problem(scene, np.zeros((5, 24, 32)), camera, FPS, ["friction"])
