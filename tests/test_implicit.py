"""The rigid body's inertial frame, and the implicit contact step (`dano.sim.implicit`)."""

import dataclasses
import importlib

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

import dano
from dano.contact import ContactParams
from dano.fields import BoxField, CapsuleField
from dano.fields.base import TransformedField
from dano.math import quat_to_mat
from dano.sim import DanoBody, Scene
from dano.sim.compile import compile_scene
from dano.sim.groups import pair_groups as implicit_groups
from dano.sim.run import Simulation, SimulationError, mechanical_energy
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


TABLE_I = [(3e4, 3e5), (1e4, 1e5), (1e4, 1e6), (1e5, 1e5), (1e5, 1e6)]
"""The paper's Table I corners (impact spring, impact damper), the defaults first."""


@pytest.mark.slow
@pytest.mark.parametrize("which", ["edge-first box", "spinning bunny"])
@pytest.mark.parametrize("spring,damper", TABLE_I)
def test_edge_first_and_round_drops_at_one_2ms_step_lose_energy_and_come_to_rest(which, spring, damper, bunny_field):
    """A box landing on an edge (turned 30 deg and 20 deg) and the bunny landing with a spin, from
    0.3 m, one 2 ms step per frame: the explicit step blew up at k = 1e4 / c = 1e5 and 1e5 / 1e5.
    `Simulation.run` audits the energy (a gain above 1 % of the scene's scale raises); here the
    total must also never exceed its start by 1 % and the body must be at rest within 2 s."""
    if which == "edge-first box":
        obj = dano.build_dano(BoxField([0.1, 0.06, 0.03]), n_points=1000, mass=0.5, log2_samples=12, replicates=4,
                              grid_resolution=0)  # fmt: skip
        body = DanoBody("b", obj, pos=(0, 0, 0.3), quat=(0.9513, 0.2549, 0.1677, -0.0449))  # xyz euler 30, 20 deg
    else:
        obj = dano.build_dano(bunny_field, n_points=1000, mass=0.7, log2_samples=12, replicates=4, grid_resolution=0)
        body = DanoBody("b", obj, pos=(0, 0, 0.3), angvel=(3.0, 1.0, 2.0))
    contact = ContactParams(impact_spring=spring, impact_damper=damper)
    sim = Simulation.from_scene(Scene(bodies=(body,), contact=contact, integrator="implicit", substeps=1, duration=2.0))
    traj = sim.run()
    names, kinetic, potential = mechanical_energy(sim, sim.params, np.asarray(traj.qpos), np.asarray(traj.qvel))
    energy = (kinetic + potential)[:, 0]
    assert energy.max() <= energy[0] + 0.01 * abs(energy[0])
    assert kinetic[-1, 0] < 1e-6 * abs(energy[0])  # at rest
    assert -_lowest(obj, np.asarray(traj.qpos[-1])) <= 2e-3  # resting penetration


def test_mechanical_energy_is_the_closed_form_and_free_flight_keeps_it(turned_box):
    """`mechanical_energy` (the energy audit's) against 1/2 m v^2 + 1/2 w.I w - m g.x of the DANO's
    own mass and inertia, a body off its principal axes, scaled; free flight keeps it (less the
    integrator's known loss)."""
    v0, w0 = np.array([0.3, -0.2, 1.0]), np.array([3.0, 1.0, 2.0])
    body = DanoBody("b", turned_box, pos=(0.1, 0.2, 0.5), quat=(0.8, 0.2, -0.4, 0.4), vel=tuple(v0), angvel=tuple(w0))
    sim = Simulation.from_scene(Scene(ground_height=None, bodies=(body,), integrator="implicit", substeps=1))
    params = dataclasses.replace(sim.params, mass_scale=jnp.asarray([2.0]), inertia_scale=jnp.asarray([1.5]))
    traj = sim.run(250, params=params)
    names, kinetic, potential = mechanical_energy(sim, params, np.asarray(traj.qpos), np.asarray(traj.qvel))
    assert names == ["b"]
    m, inertia = 2.0 * float(turned_box.mass), 3.0 * np.asarray(turned_box.inertia)
    q = np.asarray(body.quat) / np.linalg.norm(body.quat)
    R = np.asarray(quat_to_mat(jnp.asarray(q)))
    expected = 0.5 * m * v0 @ v0 + 0.5 * w0 @ (R @ inertia @ R.T) @ w0
    np.testing.assert_allclose(kinetic[0, 0], expected, rtol=1e-9)
    np.testing.assert_allclose(potential[0, 0], m * G * 0.5, rtol=1e-9)
    # Free flight: the step is symplectic Euler in gravity, which loses m (h g)^2 / 2 per step.
    total = kinetic[:, 0] + potential[:, 0] + 0.5 * m * (0.002 * G) ** 2 * np.arange(len(kinetic))
    assert np.max(np.abs(total - total[0])) < 1e-6 * total[0]


def test_energy_from_nowhere_is_a_named_simulation_error():
    """The explicit step at its first-wave defaults (4 substeps of 0.5 ms): a flat box dropped
    from 0.3 m rebounds higher than it fell. The audit stops it at the frame the energy grows and
    names the body, the ground and its penetration, and the time step."""
    obj = dano.build_dano(BoxField([0.1, 0.06, 0.03]), n_points=1000, mass=0.5, log2_samples=12, replicates=4,
                          grid_resolution=0)  # fmt: skip
    scene = Scene(bodies=(DanoBody("box", obj, pos=(0, 0, 0.3)),), integrator="explicit", substeps=4)
    sim = Simulation.from_scene(scene)
    with pytest.raises(SimulationError, match=r"energy from nowhere.*'box', touching ground \(.* mm deep\).*0\.0005 s"):
        sim.run()


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
@pytest.mark.optimized
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
    program = jax.jit(jax.value_and_grad(final_x))  # one program: the differences from its values
    grad = np.asarray(program(jnp.asarray(theta))[1])
    fd = np.asarray(partial_differences(lambda *t: program(jnp.asarray(t))[0], theta, rel_step=1e-5))
    np.testing.assert_allclose(grad, fd, rtol=2e-4, atol=1e-12)
    assert grad[0] < 0 and grad[2] > 0  # more friction, shorter slide; faster start, further


@pytest.mark.slow
def test_pairs_of_three_danos_computed_as_groups_equal_pair_by_pair(monkeypatch):
    """Three DANOs of one point count, a flat-faced box, a copy of it and a round-ended capsule, all
    turned off their axes, slide on the floor, the box and its copy into the capsule from two sides.
    The step computes the three floor pairs as one group and both box-capsule pairs as another
    (`pair_groups` across DANOs, each pair with its own velocities); pair by pair it must give the
    same motion, and its derivative w.r.t. friction must match central differences; the explicit
    step's floor pairs, grouped across the DANOs too, the same wrenches as pair by pair."""
    from dano.sim import implicit

    step_module = importlib.import_module("dano.sim.step")  # `dano.sim.step` is also the step function

    def turned(field, R):
        R, _ = np.linalg.qr(R)
        field = TransformedField(field, rotation=R * np.sign(np.linalg.det(R)))
        return dano.build_dano(field, n_points=200, mass=0.4, log2_samples=12, replicates=4, grid_resolution=16)

    box = turned(BoxField([0.1, 0.06, 0.03], width=0.002), TURNED)
    capsule = turned(CapsuleField(0.02, 0.03), TURNED.T)
    lift = [-float(np.min(np.asarray(b.body_points)[:, 2])) - 2e-4 for b in (box, capsule)]
    bodies = (
        DanoBody("box", box, pos=(-0.11, 0.0, lift[0]), vel=(1.0, 0.1, 0.0)),
        DanoBody("copy", box, pos=(0.0, 0.12, lift[0]), vel=(0.0, -1.0, 0.0)),
        DanoBody("capsule", capsule, pos=(0.0, 0.0, lift[1]), angvel=(0.0, 0.0, 2.0)),
    )
    scene = Scene(bodies=bodies, integrator="implicit", substeps=1, contact_budget=48)
    sim = Simulation.from_scene(scene)
    grouped = []

    def recorded(*args, **kwargs):
        grouped.append(implicit_groups(*args, **kwargs))
        return grouped[-1]

    monkeypatch.setattr(implicit, "pair_groups", recorded)
    monkeypatch.setattr(step_module, "pair_groups", recorded)

    def contacts():  # the explicit step's pairs (eqs. 11-16) at the start: the floor pairs press
        return jax.jit(lambda: step_module.explicit_contacts(sim.world, sim.params, sim.mjx_model, sim.data))()

    def final(mu):
        contact = tuple(dataclasses.replace(p, sliding_friction=mu) for p in sim.params.contact)
        traj = rollout(sim.world, dataclasses.replace(sim.params, contact=contact), sim.mjx_model, sim.data, 40)
        return jnp.concatenate([traj.qpos[-1], traj.qvel[-1]])

    mu0 = jnp.asarray(0.4)
    derivative = jax.jit(lambda mu: jax.jvp(final, (mu,), (jnp.ones_like(mu),)))  # a jvp: no batch of one
    x, jac = derivative(mu0)
    eps = 1e-6
    fd = (derivative(mu0 + eps)[0] - derivative(mu0 - eps)[0]) / (2 * eps)
    explicit = contacts()
    # pairs: box-floor, box-copy, box-capsule, copy-floor, copy-capsule, capsule-floor; the explicit
    # step groups no pair of two DANOs
    assert set(grouped) == {((0, 3, 5), (1,), (2, 4)), ((0, 3, 5), (1,), (2,), (4,))}
    alone_groups = lambda pair_list, *_, **__: tuple((j,) for j in range(len(pair_list)))  # noqa: E731
    monkeypatch.setattr(implicit, "pair_groups", alone_groups)
    monkeypatch.setattr(step_module, "pair_groups", alone_groups)
    alone = jax.jit(final)(mu0)

    np.testing.assert_allclose(x, alone, rtol=1e-10, atol=1e-12)
    assert min(float(explicit[0][j, 2]) for j in (0, 3, 5)) > 0.1  # every floor pair pushes up
    for a, b in zip(explicit, contacts(), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-12)
    qvel = np.asarray(x)[sim.mjx_model.nq :]
    assert qvel[0] < 1.0 - 0.4 * 9.81 * 0.08 - 0.1  # the box hit the capsule: slower than friction alone makes it
    assert qvel[13] < -0.1  # the capsule, at rest but for its spin, was pushed along -y by the copy
    assert np.all(np.abs(np.asarray(jac)) < 1e3) and np.max(np.abs(np.asarray(jac))) > 1e-3  # friction matters
    np.testing.assert_allclose(jac, fd, rtol=1e-4, atol=1e-6 * float(np.max(np.abs(fd))))


@pytest.mark.slow
def test_implicit_rollout_jacobians_over_500_frames_match_central_differences(flat_box):
    """jax.jacfwd and jax.jacrev of the final pose after 500 implicit 2 ms frames (1 s) w.r.t.
    friction, mass scale, inertia scale and the initial velocity, against central differences: a
    box pushed by a known 3 N (so the mass scale matters) while spinning (so the inertia does)."""
    lift = -float(np.min(np.asarray(flat_box.body_points)[:, 2]))
    body = DanoBody("b", flat_box, pos=(0, 0, lift), angvel=(0.0, 0.0, 2.0))
    sim = Simulation.from_scene(Scene(bodies=(body,), integrator="implicit", substeps=1))
    push = jnp.zeros((500, sim.model.nbody, 6)).at[:, sim.world.dano_body[0], 0].set(3.0)

    def final(theta):
        mu, alpha, inertia, vx = theta
        contact = dataclasses.replace(sim.params.contact[0], sliding_friction=mu)
        params = dataclasses.replace(sim.params, contact=(contact,), mass_scale=alpha[None],
                                     inertia_scale=inertia[None])  # fmt: skip
        d = sim.data.replace(qvel=sim.data.qvel.at[0].set(vx))
        q = rollout(sim.world, params, sim.mjx_model, d, 500, external=push).qpos[-1]
        return jnp.stack([q[0] + 0.3 * q[1], q[6]])  # where it went, and how far it turned

    theta = (0.2, 1.2, 1.1, 0.8)
    f = jax.jit(final)
    fd = np.stack(partial_differences(lambda *t: f(jnp.asarray(t)), theta, rel_step=1e-5), axis=1)
    for jac in (jax.jacfwd, jax.jacrev):
        J = np.asarray(jax.jit(jac(final))(jnp.asarray(theta)))
        np.testing.assert_allclose(J, fd, rtol=1e-3, atol=1e-6 * np.abs(fd).max())
    assert np.all(np.abs(fd).max(axis=0) > 1e-2)  # every parameter matters to the pose


@pytest.mark.parametrize("joint", [False, True])
@pytest.mark.parametrize("shared_normal", [False, True])
def test_analytic_friction_and_support_terms_match_autodiff(joint, shared_normal):
    """The step's Newton solve uses hand-written gradients and Hessians of friction's dissipation
    and of the normal spring + damper potential (a few matrix products over the points): check them
    against jax.grad / jax.hessian of the values, at slip speeds on both sides of v_s; some points
    held (gain 0, the hard indicator's force fixed over the step)."""
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
    gain = rng.uniform(1.0, 2e3, size=k) * (np.arange(k) % 4 > 0)  # every 4th held (the hard indicator)
    support = Support(r_a, normal, N * 1e-3, jnp.asarray(rng.uniform(-1.5, 1.5, size=k)), jnp.asarray(gain), True)
    psi, u_n0, h = N * 1e-3 * 0.5, jnp.asarray(rng.normal(size=k) * 1e-2), 0.002
    for scale in (1e-6, 1e-4, 0.3):  # slips below, near and far above v_s = 1e-5 m/s
        V = jnp.asarray(rng.normal(size=m) * scale)
        for terms in (
            lambda V: patch_terms(p, patch, V),
            lambda V: normal_terms(p, support, patch, psi, u_n0, h, V),
            lambda V: normal_terms(p, support, patch, psi, u_n0, h, V, centroid=True),
        ):
            _, g, H = terms(V)[:3]
            value = lambda V: terms(V)[0]  # noqa: B023, E731
            np.testing.assert_allclose(g, jax.grad(value)(V), rtol=1e-9, atol=1e-12 * float(jnp.max(jnp.abs(g))))
            H_auto = jax.hessian(value)(V)
            np.testing.assert_allclose(H, H_auto, rtol=1e-7, atol=1e-9 * float(jnp.max(jnp.abs(H_auto))))
