"""The rigid body's inertial frame, and the implicit contact step (`dano.sim.implicit`)."""

import dataclasses

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

import dano
from dano.contact import ContactParams
from dano.fields import BoxField
from dano.fields.base import TransformedField
from dano.math import quat_to_mat
from dano.sim import DanoBody, Scene
from dano.sim.run import Simulation
from dano.sim.scene import compile_scene
from dano.sim.step import rollout
from helpers import partial_differences

G = 9.81
TURNED = np.array(  # Rotation.from_euler("xyz", [0.4, -0.7, 1.1]): no axis of the box is a frame axis
    [[0.3456, -0.6861, -0.6402], [0.6920, -0.2757, 0.6673], [-0.6442, -0.6732, 0.3628]]
)


@pytest.fixture(scope="module")
def turned_box():
    """A box of three different sides rotated off the object frame's axes: inertia not diagonal."""
    R, _ = np.linalg.qr(TURNED)
    field = TransformedField(BoxField([0.1, 0.06, 0.03], width=0.002), rotation=R * np.sign(np.linalg.det(R)))
    return dano.build_dano(field, n_points=200, mass=0.5, log2_samples=12, replicates=4, grid_resolution=0)


@pytest.fixture(scope="module")
def flat_box():
    return dano.build_dano(BoxField([0.1, 0.1, 0.05]), n_points=1000, mass=1.0, log2_samples=12, replicates=4,
                           grid_resolution=0)  # fmt: skip


def _momentum_energy(obj, q, v):
    R = np.asarray(quat_to_mat(jnp.asarray(q[3:7])))
    w = R @ np.asarray(v[3:6])  # MuJoCo's free-joint angular velocity is in the body frame
    Iw = R @ np.asarray(obj.inertia) @ R.T
    return Iw @ w, 0.5 * w @ Iw @ w


def test_compiled_inertial_frame_is_the_principal_frame(turned_box):
    scene = Scene(bodies=(DanoBody("b", turned_box),))
    model = compile_scene(scene)[0]
    b = model.body("b").id
    assert model.body_sameframe[b] == 0 and model.body_simple[b] == 0  # MuJoCo must read body_iquat
    R = np.zeros(9)
    mujoco.mju_quat2Mat(R, model.body_iquat[b])
    R = R.reshape(3, 3)
    np.testing.assert_allclose(R @ np.diag(model.body_inertia[b]) @ R.T, turned_box.inertia, rtol=0, atol=1e-12)


@pytest.mark.parametrize("which", ["turned box", "bunny"])
def test_torque_free_asymmetric_body_keeps_its_angular_momentum(which, turned_box, bunny_field):
    if which == "turned box":
        obj = turned_box
    else:
        obj = dano.build_dano(bunny_field, n_points=200, mass=0.7, log2_samples=12, replicates=4, grid_resolution=0)
    scene = Scene(ground_height=None, gravity=(0, 0, 0), bodies=(DanoBody("b", obj, angvel=(3.0, 1.0, 2.0)),))
    # MuJoCo C with the compiled model; RK4 so that the integrator's own error is out of the way.
    model, _, _, qpos, qvel = compile_scene(scene)
    model.opt.integrator = mujoco.mjtIntegrator.mjINT_RK4
    data = mujoco.MjData(model)
    data.qpos[:], data.qvel[:] = qpos, qvel
    L0, E0 = _momentum_energy(obj, data.qpos.copy(), data.qvel.copy())
    for _ in range(int(round(1.0 / model.opt.timestep))):
        mujoco.mj_step(model, data)
    L1, E1 = _momentum_energy(obj, data.qpos, data.qvel)
    assert np.linalg.norm(L1 - L0) / np.linalg.norm(L0) < 1e-4 and abs(E1 / E0 - 1) < 1e-4
    # MJX with the implicit step (dano integrates the DANO: L held exactly, E to O(h^2)), 2 ms steps.
    traj = Simulation.from_scene(dataclasses.replace(scene, integrator="implicit", substeps=1)).run(500)
    L1, E1 = _momentum_energy(obj, np.asarray(traj.qpos[-1]), np.asarray(traj.qvel[-1]))
    assert np.linalg.norm(L1 - L0) / np.linalg.norm(L0) < 1e-4 and abs(E1 / E0 - 1) < 1e-4


def _lowest(obj, q) -> float:
    return float(np.min((np.asarray(quat_to_mat(jnp.asarray(q[3:7]))) @ np.asarray(obj.body_points).T)[2]) + q[2])


@pytest.mark.slow
@pytest.mark.parametrize("spring,damper", [(3e4, 3e5), (1e4, 1e5), (1e4, 1e6), (1e5, 1e5), (1e5, 1e6)])
def test_flat_box_dropped_at_one_2ms_step_per_frame_never_gains_energy(flat_box, spring, damper):
    lift = -float(np.min(np.asarray(flat_box.body_points)[:, 2]))
    contact = ContactParams(impact_spring=spring, impact_damper=damper)
    body = DanoBody("b", flat_box, pos=(0, 0, 0.3 + lift))
    scene = Scene(bodies=(body,), contact=contact, integrator="implicit", substeps=1, duration=1.2)
    traj = Simulation.from_scene(scene).run()
    q, v = np.asarray(traj.qpos), np.asarray(traj.qvel)
    inertia = np.asarray(flat_box.inertia)
    spin = 0.5 * np.einsum("ti,ij,tj->t", v[:, 3:], inertia, v[:, 3:])
    energy = 0.5 * np.sum(v[:, :3] ** 2, axis=1) + spin + G * q[:, 2]
    assert energy.max() <= energy[0] * 1.01  # explicit at 0.5 ms: rebounds higher than it fell
    assert np.linalg.norm(v[-1, :3]) < 1e-3  # at rest
    assert -min(_lowest(flat_box, row) for row in q) <= 2e-3  # penetration


def test_friction_holds_a_box_on_a_20_degree_slope(flat_box):
    th = np.radians(20.0)  # tan 20 = 0.36 < mu = 0.5: it must stick (MuJoCo C's defaults creep 1.8 mm/s)
    normal, quat = (np.sin(th), 0.0, np.cos(th)), (np.cos(th / 2), 0.0, np.sin(th / 2), 0.0)
    lift = -float(np.min(np.asarray(flat_box.body_points)[:, 2]))
    body = DanoBody("b", flat_box, pos=tuple(lift * np.asarray(normal)), quat=quat)
    scene = Scene(ground_normal=normal, bodies=(body,), integrator="implicit", substeps=1, duration=3.0,
                  contact=ContactParams(sliding_friction=0.5))  # fmt: skip
    x = np.asarray(Simulation.from_scene(scene).run().qpos[:, :3]) @ np.array([np.cos(th), 0.0, -np.sin(th)])
    creep = (x[-1] - x[500]) / 2.0  # m/s over the last 2 s
    assert abs(creep) <= 1e-4  # m/s: 0.1 mm/s (the bound; measured 0.01 mm/s)


@pytest.mark.parametrize("sunk", [0.0, 1e-3])
def test_a_box_placed_on_or_into_the_floor_is_not_launched_and_slides_v2_over_2_mu_g(flat_box, sunk):
    lift = -float(np.min(np.asarray(flat_box.body_points)[:, 2]))
    mu, v0 = 0.5, 1.0
    body = DanoBody("b", flat_box, pos=(0, 0, lift - sunk), vel=(v0, 0, 0))
    scene = Scene(bodies=(body,), integrator="implicit", substeps=1, duration=0.6,
                  contact=ContactParams(sliding_friction=mu))  # fmt: skip
    traj = Simulation.from_scene(scene).run()
    q, v = np.asarray(traj.qpos), np.asarray(traj.qvel)
    assert max(_lowest(flat_box, row) for row in q) <= 1e-3  # explicit: launched to 46 mm clear
    assert np.linalg.norm(v[-1, :3]) < 1e-3  # stopped
    # v0^2 / (2 mu g); backward Euler's x += h v' alone is h v0 / 2 = 1 % short.
    np.testing.assert_allclose(q[-1, 0], v0**2 / (2 * mu * G), rtol=0.02)


def test_a_box_on_a_slope_with_mu_below_tan_theta_accelerates_at_g_sin_minus_mu_cos(flat_box):
    th, mu = np.radians(20.0), 0.3
    normal, quat = (np.sin(th), 0.0, np.cos(th)), (np.cos(th / 2), 0.0, np.sin(th / 2), 0.0)
    lift = -float(np.min(np.asarray(flat_box.body_points)[:, 2]))
    body = DanoBody("b", flat_box, pos=tuple(lift * np.asarray(normal)), quat=quat)
    scene = Scene(ground_normal=normal, bodies=(body,), integrator="implicit", substeps=1, duration=1.5,
                  contact=ContactParams(sliding_friction=mu))  # fmt: skip
    v = np.asarray(Simulation.from_scene(scene).run().qvel[:, :3]) @ np.array([np.cos(th), 0.0, -np.sin(th)])
    accel = np.polyfit(np.arange(250, 750) * 0.002, v[250:750], 1)[0]
    np.testing.assert_allclose(accel, G * (np.sin(th) - mu * np.cos(th)), rtol=0.02)


@pytest.mark.slow
def test_the_top_of_two_stacked_boxes_stays_put():
    """DANO on DANO on the floor for 10 s (eqs. 9-10, solved jointly): the top box holds."""
    flat_box = dano.build_dano(BoxField([0.1, 0.1, 0.05]), n_points=1000, mass=1.0, log2_samples=12,
                               replicates=4, grid_resolution=32)  # fmt: skip
    lift = -float(np.min(np.asarray(flat_box.body_points)[:, 2]))
    bodies = (DanoBody("bottom", flat_box, pos=(0, 0, lift)), DanoBody("top", flat_box, pos=(0.01, 0, 3 * lift)))
    traj = Simulation.from_scene(Scene(bodies=bodies, integrator="implicit", substeps=1, duration=10.0)).run()
    top = np.asarray(traj.qpos)[:, 7:10]
    drift = np.linalg.norm(top[-1, :2] - top[1000, :2]) / 8.0  # m/s over the last 8 s
    assert drift <= 1e-5  # the bound, 0.01 mm/s (the explicit step: 0.06-0.07 mm/s)
    assert abs(top[-1, 2] - top[1000, 2]) < 1e-4  # not sinking into the bottom box


def test_implicit_step_gradients_match_central_differences(flat_box):
    """d(final x)/d(friction, damper, initial velocity) through 40 implicit steps of a sliding box
    (Newton's friction solve differentiated through its optimality condition)."""
    lift = -float(np.min(np.asarray(flat_box.body_points)[:, 2]))
    scene = Scene(bodies=(DanoBody("b", flat_box, pos=(0, 0, lift - 2e-4)),), integrator="implicit", substeps=1)
    sim = Simulation.from_scene(scene)

    def final_x(theta):
        mu, damper, vx = theta
        contact = dataclasses.replace(sim.params.contact[0], sliding_friction=mu, impact_damper=damper)
        params = dataclasses.replace(sim.params, contact=(contact,))
        d = sim.data.replace(qvel=sim.data.qvel.at[0].set(vx))
        return rollout(sim.world, params, sim.mjx_model, d, 40).qpos[-1, 0]

    theta = (0.5, 3e5, 0.5)
    grad = np.asarray(jax.jit(jax.grad(final_x))(jnp.asarray(theta)))
    f = jax.jit(final_x)
    fd = np.asarray(partial_differences(lambda *t: f(jnp.asarray(t)), theta, rel_step=1e-5))
    np.testing.assert_allclose(grad, fd, rtol=2e-4, atol=1e-12)
    assert grad[0] < 0 and grad[2] > 0  # more friction, shorter slide; faster start, further


@pytest.mark.parametrize("joint", [False, True])
@pytest.mark.parametrize("shared_normal", [False, True])
def test_analytic_friction_and_support_terms_match_autodiff(joint, shared_normal):
    """The step's Newton solve uses hand-written gradients and Hessians of friction's dissipation
    and of the normal spring + damper potential (a few matrix products over the points): check them
    against jax.grad / jax.hessian of the values, at slip speeds on both sides of v_s."""
    from dano.contact.friction import Patch, patch_terms
    from dano.contact.support import Support, normal_terms

    rng = np.random.default_rng(3)
    k, m = 40, 12 if joint else 6
    r_a = jnp.asarray(rng.normal(size=(3, k)) * 0.05)
    r_b = jnp.asarray(rng.normal(size=(3, k)) * 0.05) if joint else jnp.zeros((3, k))
    u_b = jnp.zeros((3, k)) if joint else jnp.asarray(rng.normal(size=(3, k)) * 1e-5)
    w_b = jnp.zeros(3) if joint else jnp.asarray(rng.normal(size=3) * 1e-3)
    normal = rng.normal(size=(3, 1 if shared_normal else k))
    normal = jnp.asarray(normal / np.linalg.norm(normal, axis=0))
    N = jnp.asarray(rng.uniform(0.0, 2.0, size=k))
    patch = Patch(r_a, r_b, u_b, w_b, normal, N, joint)
    p = ContactParams(sliding_friction=0.4, torsional_friction=0.02, rolling_friction=0.01, sliding_drag=0.3)
    support = Support(r_a, normal, N * 1e-3, jnp.asarray(rng.uniform(-1.5, 1.5, size=k)),
                      jnp.asarray(rng.uniform(1.0, 2e3, size=k)), True)  # fmt: skip
    psi, u_n0, h = N * 1e-3 * 0.5, jnp.asarray(rng.normal(size=k) * 1e-2), 0.002
    for scale in (1e-6, 1e-4, 0.3):  # slips below, near and far above v_s = 1e-5 m/s
        V = jnp.asarray(rng.normal(size=m) * scale)
        for terms in (lambda V: patch_terms(p, patch, V), lambda V: normal_terms(p, support, patch, psi, u_n0, h, V)):
            _, g, H = terms(V)[:3]
            value = lambda V: terms(V)[0]  # noqa: B023, E731
            np.testing.assert_allclose(g, jax.grad(value)(V), rtol=1e-9, atol=1e-12 * float(jnp.max(jnp.abs(g))))
            H_auto = jax.hessian(value)(V)
            np.testing.assert_allclose(H, H_auto, rtol=1e-7, atol=1e-9 * float(jnp.max(jnp.abs(H_auto))))
