"""Renders of simulations: DANOs drawn as their surfaces, framed so that they fill the picture."""

import equinox as eqx
import mujoco
import numpy as np
import pytest

from dano import build_dano
from dano.errors import DanoError
from dano.fields import BoxField
from dano.sim import DanoBody, Primitive, Scene
from dano.sim.render import draw_frame, frame_camera, make_renderer, render_video, scene_model
from dano.sim.run import Simulation
from dano.sim.scene import Mode
from dano.surface import surface_mesh

SIZE = (0.09, 0.06, 0.03)


@pytest.fixture(scope="module")
def soap():
    return build_dano(BoxField(size=SIZE), mass=0.1, n_points=300)


def test_the_surface_mesh_is_the_box_about_its_centre_of_mass(soap):
    mesh = surface_mesh(soap, resolution=48)
    assert mesh.is_watertight and mesh.volume > 0
    # Marching cubes at the middle of the density window: the box's faces, to within a voxel.
    voxel = max(SIZE) / 47 * 1.5
    np.testing.assert_allclose(mesh.extents, SIZE, atol=2 * voxel)
    np.testing.assert_allclose(mesh.center_mass, 0.0, atol=1e-3)  # body frame: origin at the centre of mass
    blind = eqx.tree_at(lambda d: d.grid, soap, None, is_leaf=lambda x: x is None)
    with pytest.raises(DanoError, match="no density grid to mesh"):
        surface_mesh(blind)


def _picture(sim, traj, style, segmentation=False):
    model, clouds = scene_model(sim, style)
    qpos = np.asarray(traj.qpos)
    camera = frame_camera(model, qpos, sim)
    renderer = make_renderer(model, 240, 320, max_geom=10000)
    if segmentation:
        renderer.enable_segmentation_rendering()
    picture = draw_frame(renderer, model, mujoco.MjData(model), qpos[-1], camera, sim, clouds)
    renderer.close()
    return model, clouds, picture


def test_a_dano_is_drawn_as_its_surface_and_the_camera_frames_what_moves(soap):
    # A bar of soap lying still, and a ball rolling past it: both stay in the picture, the soap a
    # surface covering a good part of it.
    ball = Primitive("ball", "sphere", (0.02,), pos=(-0.15, 0.05, 0.02), mode=Mode.free, mass=0.2, vel=(1.0, 0, 0))
    scene = Scene(duration=0.2, bodies=(DanoBody("soap", soap, pos=(0.0, 0.0, 0.015)),), primitives=(ball,))
    sim = Simulation.from_scene(scene)
    traj = sim.run()
    model, clouds, seg = _picture(sim, traj, "surface", segmentation=True)
    assert clouds == [None] and model.ngeom == sim.model.ngeom + 1  # the surface: one visual geom
    soap_geom, ball_geom = model.geom("soap_surface").id, model.body_geomadr[model.body("ball").id]
    assert model.geom_contype[soap_geom] == model.geom_conaffinity[soap_geom] == 0  # drawn, not collided
    geoms = np.where(seg[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM), seg[..., 0], -1)
    assert np.mean(geoms == soap_geom) > 0.05
    assert np.mean(geoms == ball_geom) > 0.002  # the ball, where it ended, is in view
    # Points instead: no mesh in the model, the points drawn as spheres.
    model, clouds, picture = _picture(sim, traj, "points")
    assert model.nmesh == sim.model.nmesh and clouds[0] is not None and len(clouds[0]) == 300
    assert picture.shape == (240, 320, 3) and picture.std() > 0


def test_a_dano_without_a_grid_is_drawn_as_points_and_a_bad_style_is_named(soap, tmp_path):
    blind = eqx.tree_at(lambda d: d.grid, soap, None, is_leaf=lambda x: x is None)
    sim = Simulation.from_scene(Scene(duration=0.01, bodies=(DanoBody("soap", blind, pos=(0.0, 0.0, 0.015)),)))
    model, clouds = scene_model(sim)
    assert clouds[0] is not None and model.nmesh == 0
    with pytest.raises(DanoError, match="style.*'surface', 'points'"):
        render_video(sim, sim.run(), tmp_path / "v.mp4", style="mesh", progress=False)
    assert list(tmp_path.iterdir()) == []


def _red(picture: np.ndarray) -> np.ndarray:
    """Pixels far redder than green: the arrows (red, lit), not the orange soap nor the floor."""
    return picture[..., 0].astype(int) - picture[..., 1].astype(int) > 100


def test_contact_forces_are_drawn_as_arrows_from_where_they_act(soap, tmp_path):
    # The soap resting on the floor: one arrow, up from its bottom face, its weight half its size long.
    from dano.sim.contacts import contact_forces
    from dano.sim.render import SEE_THROUGH, contact_arrows

    scene = Scene(duration=0.3, bodies=(DanoBody("soap", soap, pos=(0.0, 0.0, 0.016)),))
    sim = Simulation.from_scene(scene)
    traj = sim.run()
    forces = contact_forces(sim, traj)
    arrows = contact_arrows(sim, forces)
    assert arrows.shape == (len(traj.qpos), 1, 3, 3)
    start, end, width = arrows[-1, 0]
    x = np.asarray(traj.qpos[-1, :3])
    np.testing.assert_allclose(start[2], x[2] - SIZE[2] / 2, atol=2e-3)  # on the bottom face
    np.testing.assert_allclose(end - start, [0.0, 0.0, 0.5 * SIZE[0]], atol=2e-3)  # its weight: half its size
    assert width[0] > 0
    model, clouds = scene_model(sim, alpha=SEE_THROUGH)
    camera = frame_camera(model, np.asarray(traj.qpos), sim)
    renderer = make_renderer(model, 240, 320, max_geom=10000)
    data = mujoco.MjData(model)
    plain = draw_frame(renderer, model, data, np.asarray(traj.qpos[-1]), camera, sim, clouds)
    drawn = draw_frame(renderer, model, data, np.asarray(traj.qpos[-1]), camera, sim, clouds, arrows[-1])
    renderer.close()
    assert _red(plain).sum() == 0 and _red(drawn).sum() > 50
    rows, cols = np.nonzero(_red(drawn))
    assert 60 < cols.mean() < 260 and rows.mean() < 200  # in the middle, where the soap is
    path = render_video(sim, traj, tmp_path / "v.gif", progress=False, contacts=forces, fps=10.0)
    assert path.exists()
    with pytest.raises(DanoError, match="contact forces have 2 frames, the trajectory 151"):
        render_video(sim, traj, tmp_path / "w.gif", progress=False, contacts=contact_forces(sim, sim.run(1)))
