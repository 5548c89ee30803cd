from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dano
from dano.contact import ContactParams
from dano.fields import BoxField
from dano.math import quat_to_mat
from dano.sim import DanoBody, Params, Primitive, Scene
from dano.sim.run import Simulation, SimulationError
from dano.sim.scene import DEFAULT_SUBSTEPS
from dano.sim.step import rollout
from helpers import partial_differences, with_value

G = 9.81


@pytest.fixture(scope="module")
def cube():
    return dano.build_dano(BoxField([0.1, 0.1, 0.1], width=0.002), n_points=2000, mass=1.0, log2_samples=13)


def _rest_height(d) -> float:
    """Centre-of-mass height at which the lowest sample point touches z = 0."""
    return -float(jnp.min(d.body_points[:, 2]))


def test_free_fall_and_torque_free_rotation(cube):
    scene = Scene(
        ground_height=None, bodies=(DanoBody("c", cube, pos=(0, 0, 1), vel=(0.3, 0, 1), angvel=(0.4, -1, 2)),)
    )
    traj = Simulation.from_scene(scene).run(150)
    t = 150 * scene.timestep
    h = scene.step_size
    # Semi-implicit Euler: z_n = z0 + v0 t - g t (t + h) / 2, an O(h) offset from the closed form.
    z_closed = 1 + t - G * t * t / 2
    assert float(traj.qpos[-1, 2]) == pytest.approx(z_closed - G * t * h / 2, abs=1e-9)
    assert abs(float(traj.qpos[-1, 2]) - z_closed) <= G * t * h / 2 + 1e-9
    assert float(traj.qpos[-1, 0]) == pytest.approx(0.3 * t, rel=1e-12)

    # Without torque the world angular momentum R J R^T w is conserved (to the integrator's error).
    def momentum(q, v):
        R = quat_to_mat(q[3:7])
        return R @ cube.inertia @ v[3:6]  # MuJoCo's free-joint angular velocity is in the body frame

    L0, L1 = momentum(traj.qpos[0], traj.qvel[0]), momentum(traj.qpos[-1], traj.qvel[-1])
    np.testing.assert_allclose(L1, L0, rtol=1e-3)
    np.testing.assert_allclose(quat_to_mat(traj.qpos[0, 3:7]) @ traj.qvel[0, 3:6], [0.4, -1, 2], rtol=1e-12)


def _slide(
    cube,
    smoothing: float,
    mode: Literal["points", "centroid"] = "points",
    integrator: Literal["implicit", "explicit"] = "explicit",
):
    """A 1 m/s slide at mu 0.5; the explicit step by default (its smoothed Coulomb law is what
    `coulomb_smoothing` sets; the implicit step's law has no such parameter)."""
    contact = ContactParams(sliding_friction=0.5, coulomb_smoothing=smoothing)
    body = DanoBody("c", cube, pos=(0, 0, _rest_height(cube)), vel=(1.0, 0, 0))
    scene = Scene(bodies=(body,), contact=contact, force_mode=mode, integrator=integrator,
                  substeps=DEFAULT_SUBSTEPS[integrator])  # fmt: skip
    return Simulation.from_scene(scene).run(500)


@pytest.mark.parametrize("integrator", ["explicit", "implicit"])
def test_box_slides_v2_over_2_mu_g_and_stops(cube, integrator):
    # With a sharp Coulomb law (s = 1000 s/m) friction is mu N down to ~3 mm/s: within 5 % of v^2/(2 mu g);
    # the implicit step's law is sharp at any smoothing.
    traj = _slide(cube, smoothing=1000.0, integrator=integrator)
    distance = float(traj.qpos[-1, 0])
    assert distance == pytest.approx(1 / (2 * 0.5 * G), rel=0.05)
    assert float(jnp.linalg.norm(traj.qvel[-1, :3])) < 1e-3
    assert abs(float(traj.qpos[-1, 1])) < 1e-3  # no sideways drift


def test_slide_matches_the_smoothed_coulomb_law(cube):
    # With the default s = 30 s/m dry friction fades below ~0.1 m/s, and below eps it is quadratic in
    # the speed, so the box creeps on (the paper's creep). The exact distance of that law down to
    # the final simulated speed v_end is int_{v_end}^{1} v dv / (mu g c(v)),
    # c(v) = (2/pi) atan(s v) v / (eps + v). Tolerance 2 %: time step, rocking on the shell.
    traj = _slide(cube, smoothing=30.0)
    v_end = float(jnp.linalg.norm(traj.qvel[-1, :3]))
    v = np.geomspace(v_end, 1.0, 20001)
    c = (2 / np.pi) * np.arctan(30 * v) * v / (1e-3 + v)
    expected = np.trapezoid(v / (0.5 * G * c), v)
    assert float(traj.qpos[-1, 0]) == pytest.approx(expected, rel=0.02)


@pytest.mark.slow
def test_bunny_dropped_comes_to_rest(bunny_field):
    bunny = dano.build_dano(bunny_field, n_points=5000, mass=0.7)
    z0 = 0.1 + _rest_height(bunny)
    sim = Simulation.from_scene(Scene(bodies=(DanoBody("b", bunny, pos=(0, 0, z0), angvel=(0.5, 0, 3.0)),)))
    traj = sim.run(1000)
    speed = np.linalg.norm(np.asarray(traj.qvel[:, :3]), axis=1)
    assert np.all(speed[500:] < 1e-3)  # at rest within 1 s (acceptance: 2 s)
    lows = [float(jnp.min((quat_to_mat(q[3:7]) @ bunny.body_points.T)[2]) + q[2]) for q in traj.qpos[::20]]
    assert -min(lows) < 2e-3  # penetration below 2 mm


def test_sphere_pushes_the_dano_the_right_way(cube):
    # A driven (mocap) sphere moving along +x into a resting cube pushes it along +x.
    z = _rest_height(cube)
    sphere = Primitive("pusher", "sphere", (0.03,), pos=(-0.09, 0, z), mode="mocap")
    sim = Simulation.from_scene(Scene(bodies=(DanoBody("c", cube, pos=(0, 0, z)),), primitives=(sphere,)))
    n = 200
    path = jnp.stack([jnp.linspace(-0.09, 0.0, n), jnp.zeros(n), jnp.full(n, z)], axis=1)[:, None, :]
    traj = eqx.filter_jit(rollout)(sim.world, sim.params, sim.mjx_model, sim.data, n, None, path)
    assert float(traj.qpos[-1, 0]) > 0.02
    assert abs(float(traj.qpos[-1, 1])) < 0.2 * float(traj.qpos[-1, 0])


def test_free_sphere_collision_conserves_momentum(cube):
    sphere = Primitive("ball", "sphere", (0.03,), pos=(-0.2, 0.01, 0.005), mode="free", mass=0.5, vel=(2.0, 0, 0))
    scene = Scene(ground_height=None, gravity=(0, 0, 0), bodies=(DanoBody("c", cube),), primitives=(sphere,))
    sim = Simulation.from_scene(scene)
    traj = sim.run(150)
    mass = np.array([1.0, 0.5])
    p0 = mass @ np.stack([traj.qvel[0, 0:3], traj.qvel[0, 6:9]])
    p1 = mass @ np.stack([traj.qvel[-1, 0:3], traj.qvel[-1, 6:9]])
    assert float(traj.qvel[-1, 0]) > 0.3  # the cube was hit
    np.testing.assert_allclose(p1, p0, atol=1e-6 * float(np.linalg.norm(p0)))


def test_blow_up_is_reported_with_the_frame(cube):
    """The explicit step with a spring far too stiff for its 2 ms step (the implicit one holds it)."""
    stiff = ContactParams(impact_spring=1e7, impact_damper=1e8)
    body = DanoBody("c", cube, pos=(0, 0, 0.05), vel=(0, 0, -2))
    sim = Simulation.from_scene(Scene(bodies=(body,), contact=stiff, substeps=1, integrator="explicit"))
    with pytest.raises(SimulationError, match=r"frame \d+ .*'c'.* 0.002 s"):  # the frame, the body, the step
        sim.run(100)


@pytest.mark.parametrize("integrator", ["explicit", "implicit"])
def test_vmap_of_rollouts_equals_a_loop(cube, integrator):
    body = DanoBody("c", cube, pos=(0, 0, _rest_height(cube)))
    scene = Scene(bodies=(body,), integrator=integrator, substeps=DEFAULT_SUBSTEPS[integrator])
    sim = Simulation.from_scene(scene)

    def final_x(vx):
        d = sim.data.replace(qvel=sim.data.qvel.at[0].set(vx))
        return rollout(sim.world, sim.params, sim.mjx_model, d, 50).qpos[-1, :3]

    speeds = jnp.asarray([0.2, 0.5, 0.9])
    batched = jax.jit(jax.vmap(final_x))(speeds)
    looped = jnp.stack([jax.jit(final_x)(v) for v in speeds])
    np.testing.assert_allclose(batched, looped, rtol=1e-10, atol=1e-12)


def test_a_batch_on_lanes_equals_the_vmapped_batch(cube, monkeypatch):
    """`Simulation.run_batch` with each environment by the single-environment program on parallel
    lanes (the default on one CPU device) equals the vmapped batch, environment by environment;
    the environments differ (faster starts slide further). Two lanes: 2 + 1 environments, padded."""
    monkeypatch.setenv("DANO_LANES", "2")
    sim = Simulation.from_scene(Scene(bodies=(DanoBody("c", cube, pos=(0, 0, _rest_height(cube))),)))
    batch = sim.batch_data(3)
    batch = batch.replace(qvel=batch.qvel.at[:, 0].set(jnp.asarray([0.2, 0.5, 0.9])))
    on_lanes, vmapped = sim.run_batch(batch, 40, vmap=False), sim.run_batch(batch, 40, vmap=True)
    assert on_lanes.qpos.shape == vmapped.qpos.shape == (3, 41, 7)
    np.testing.assert_allclose(on_lanes.qpos, vmapped.qpos, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(on_lanes.qvel, vmapped.qvel, rtol=1e-9, atol=1e-10)
    assert np.all(np.diff(np.asarray(on_lanes.qpos[:, -1, 0])) > 1e-3)
    with pytest.raises(SimulationError, match="at least one environment"):
        sim.run_batch(sim.batch_data(0), 5)


@pytest.mark.slow
def test_rollout_gradients_match_finite_differences(cube):
    """d(final position)/d(friction, mass scale, initial velocity) through 500 steps, float64.

    A known push (3 N along x, paper footnote 1) makes the mass scale matter."""
    z = _rest_height(cube)
    sim = Simulation.from_scene(Scene(substeps=1, timestep=0.0005, bodies=(DanoBody("c", cube, pos=(0, 0, z)),)))

    def loss(mu, alpha, vx):
        contact = (ContactParams(sliding_friction=mu, indicator_width=2e-3),)
        params = Params(contact=contact, mass_scale=jnp.stack([alpha]), inertia_scale=sim.params.inertia_scale)
        d = sim.data.replace(qvel=sim.data.qvel.at[0].set(vx))
        push = jnp.zeros((500, sim.model.nbody, 6)).at[:, 1, 0].set(3.0)
        q = rollout(sim.world, params, sim.mjx_model, d, 500, external=push).qpos[-1]
        return q[0] + 0.3 * q[1] + 0.1 * q[2]

    x0 = (0.4, 1.2, 0.8)
    grads = jax.jit(jax.grad(loss, argnums=(0, 1, 2)))(*x0)
    for i, (g, fd) in enumerate(zip(grads, partial_differences(jax.jit(loss), x0), strict=True)):
        assert float(g) == pytest.approx(float(fd), rel=1e-4), i
        assert abs(float(g)) > 1e-3, i


@pytest.mark.parametrize("integrator", ["implicit", "explicit"])
def test_per_point_forces_resist_spin_without_torsional_friction(cube, integrator):
    """The paper's limitation (i): with forces at the single centroid, nothing but the torsional
    coefficient resists spinning; applied per point, sliding friction does, as on a real face.

    A cube spinning at w0 on its face with dry friction mu stops after turning w0^2 I / (2 mu m g r),
    r = 0.3826 a the mean distance of a square face of side a from its centre: 6.4 deg here. In
    centroid mode the only brake is friction at chi, which the sampled face puts a little off the
    axis: the explicit step's smoothed law hardly feels that slip (1.35 rad/s left after 1 s), the
    implicit step's sharp one does (0.46 rad/s left), and both are far from stopping.
    """
    contact = ContactParams(torsional_friction=0.0, rolling_friction=0.0)
    body = DanoBody("c", cube, pos=(0, 0, _rest_height(cube)), angvel=(0, 0, 5.0))
    turned = {}
    for mode in ("points", "centroid"):
        scene = Scene(bodies=(body,), contact=contact, force_mode=mode, integrator=integrator)
        traj = Simulation.from_scene(scene).run(500)
        turned[mode] = np.degrees(2 * np.arctan2(float(traj.qpos[-1, 6]), float(traj.qpos[-1, 3])))
        spin = float(traj.qvel[-1, 5])
        if mode == "points":
            assert abs(spin) < 0.01
        else:
            assert spin > (1.0 if integrator == "explicit" else 0.25)  # still spinning after 1 s
    inertia = float(cube.inertia[2, 2])
    expected = np.degrees(25 * inertia / (2 * 0.5 * 1.0 * G * 0.3826 * 0.1))
    if integrator == "explicit":
        # The smoothed Coulomb law is weaker than dry friction below ~0.1 m/s: it turns further.
        assert expected < turned["points"] < 1.6 * expected
    else:  # dry friction to within the stiction velocity: the closed form (measured 0.7 % short)
        assert abs(turned["points"] / expected - 1.0) < 0.03


def test_slope_with_any_ground_normal(cube):
    """A box on a 20 degree slope (ground normal tilted about y): it stays for mu > tan 20 and
    slides with a = g (sin - mu cos) for mu < tan 20 (sharp Coulomb law: s = 1000 s/m).

    The acceleration is measured between 0.25 and 0.5 s: in the first ~50 ms the box settles into
    the penalty layer, with less normal force (so less friction) than at rest.
    """
    theta = np.radians(20.0)
    normal = (float(np.sin(theta)), 0.0, float(np.cos(theta)))
    quat = (float(np.cos(theta / 2)), 0.0, float(np.sin(theta / 2)), 0.0)  # box face on the slope
    x, y, z = (float(v) for v in _rest_height(cube) * np.asarray(normal))
    pos = (x, y, z)
    downhill = np.array([np.cos(theta), 0.0, -np.sin(theta)])
    for mu in (0.2, 0.6):
        contact = ContactParams(sliding_friction=mu, coulomb_smoothing=1000.0)
        scene = Scene(bodies=(DanoBody("c", cube, pos=pos, quat=quat),), ground_normal=normal, contact=contact)
        traj = Simulation.from_scene(scene).run(250)
        speed = np.asarray(traj.qvel[:, :3]) @ downhill
        if mu < np.tan(theta):
            accel = (speed[250] - speed[125]) / 0.25
            assert accel == pytest.approx(G * (np.sin(theta) - mu * np.cos(theta)), rel=0.02)
        else:
            # It holds, but the smoothed law has no stiction: it creeps at the speed where
            # mu c(v) = tan(theta), c(v) = (2/pi) atan(s v) v / (eps + v) (the paper's creep).
            v = np.geomspace(1e-6, 1.0, 200001)
            creep = v[np.argmax(mu * (2 / np.pi) * np.arctan(1000 * v) * v / (1e-3 + v) > np.tan(theta))]
            assert abs(speed[-1]) < 1.5 * creep


def test_actuated_sphere_pushes_with_a_known_force(cube):
    z = _rest_height(cube)
    pusher = Primitive("ee", "sphere", (0.03,), pos=(-0.09, 0.0, z), mode="actuated", mass=1.0)
    contact = ContactParams(sliding_friction=0.3)
    sim = Simulation.from_scene(
        Scene(bodies=(DanoBody("c", cube, pos=(0, 0, z)),), primitives=(pusher,), contact=contact)
    )
    assert sim.model.nu == 3
    n = 300
    ctrl = jnp.zeros((n, 3)).at[:, 0].set(6.0)  # 6 N along +x; friction holds the 1 kg cube at 2.9 N
    traj = sim.run(n, ctrl=ctrl)
    assert float(traj.qpos[-1, 0]) > 0.03
    a = sim.world.prims[0].qpos
    gap = float(traj.qpos[-1, 0]) - (-0.09 + float(traj.qpos[-1, a]))
    assert gap == pytest.approx(0.03 + 0.05, abs=0.005)  # the sphere stays in contact with the face


def test_jacfwd_and_vmap_over_parameters_and_controls(cube):
    """jacfwd w.r.t. the inertia scale and a control sequence vs central differences; vmap over the
    parameters (friction among them) equals the unbatched rollout."""
    z = _rest_height(cube)
    pusher = Primitive("ee", "sphere", (0.03,), pos=(-0.085, 0.01, z), mode="actuated", mass=1.0)
    body = DanoBody("c", cube, pos=(0, 0, z))
    sim = Simulation.from_scene(Scene(substeps=2, bodies=(body,), primitives=(pusher,)))
    n = 60

    def final(inertia_scale, force, mu):
        contact = tuple(eqx.tree_at(lambda c: c.sliding_friction, p, mu) for p in sim.params.contact)
        params = Params(contact=contact, mass_scale=sim.params.mass_scale, inertia_scale=jnp.stack([inertia_scale]))
        ctrl = jnp.zeros((n, 3)).at[:, 0].set(force)
        q = rollout(sim.world, params, sim.mjx_model, sim.data, n, ctrl=ctrl).qpos[-1]
        return jnp.stack([q[0], q[1], q[6]])  # x, y and a quaternion component (the cube yaws)

    x0 = (1.0, 8.0, 0.4)
    # One program for the derivatives (with the value at x0 beside them) and one vmapped over all
    # three arguments for everything else: the central differences and the frictions in one batch.
    jac, value = eqx.filter_jit(jax.jacfwd(with_value(final), argnums=(0, 1), has_aux=True))(*x0)
    h = 1e-5 * np.array([1.0, 8.0])
    points = [x0, (1.0 + h[0], 8.0, 0.4), (1.0 - h[0], 8.0, 0.4), (1.0, 8.0 + h[1], 0.4), (1.0, 8.0 - h[1], 0.4),
              (1.0, 8.0, 0.2), (1.0, 8.0, 0.8)]  # fmt: skip
    batched = np.asarray(
        eqx.filter_jit(jax.vmap(final))(*(jnp.asarray(column) for column in zip(*points, strict=True)))
    )
    fds = [(batched[1] - batched[2]) / (2 * h[0]), (batched[3] - batched[4]) / (2 * h[1])]
    for J, fd in zip(jac, fds, strict=True):
        # atol: central differences lose ~1e-5 of the largest entry to round-off; the sideways and
        # yaw entries are ~100x smaller than the push direction's.
        np.testing.assert_allclose(np.asarray(J), fd, rtol=1e-4, atol=1e-5 * np.max(np.abs(fd)))
        assert np.max(np.abs(fd)) > 1e-6
    # vmap over the parameters equals the unbatched rollout (the value beside the derivatives);
    # friction changes where the cube ends
    np.testing.assert_allclose(batched[0], value, rtol=1e-10, atol=1e-13)
    assert abs(batched[5, 0] - batched[6, 0]) > 1e-3  # 11 mm measured (0.2 vs 0.8)
