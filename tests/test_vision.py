"""From pixels: fitting a field to rendered views, solidifying it, tracking a rendered video."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

import dano
from dano.fields import GridField, mesh_field
from dano.fields.grid import grid_nodes
from dano.math import quat_exp
from dano.vision import camera_from_fov, load_masks, load_nerf_synthetic, look_at, render_mesh_video, render_views
from dano.vision.fit import FitConfig, FitError, GridModel, fit_field, solidify
from dano.vision.track import (
    TrackConfig,
    TrackError,
    crop,
    downsample,
    mask_loss,
    refine,
    render_silhouette,
    silhouette,
    track,
    windows,
)

BOX = trimesh.creation.box((0.08, 0.05, 0.04))


def _principal_per_mass(mesh):
    exact = mesh.copy()
    exact.density = 1.0 / mesh.volume
    return np.sort(np.linalg.eigvalsh(exact.moment_inertia))


@pytest.mark.slow
@pytest.mark.optimized
def test_a_box_fitted_from_24_small_views_is_a_solid_box(tmp_path):
    render_views(BOX, tmp_path / "views", n_views=24, resolution=32, progress=False)
    views = load_nerf_synthetic(tmp_path / "views")
    config = FitConfig(GridModel(resolution=32), steps=300, n_samples=64)
    result = fit_field(views, config, key=jax.random.key(0), progress=False)
    assert result.psnr[-20:].mean() > 20.0
    assert isinstance(result.field, GridField)
    solid = solidify(result.field, views)
    d = dano.build_dano(solid.field, n_points=1000, mass=1.0)
    # One 32 px pixel is ~2.5 mm on the box; its half-sizes are 20-40 mm: moments within 15 %.
    np.testing.assert_allclose(np.asarray(d.com), 0.0, atol=2.5e-3)
    np.testing.assert_allclose(np.asarray(d.principal_moments()), _principal_per_mass(BOX), rtol=0.15)
    # The same seed, the same field (a short fit twice: the rays drawn, the samples and the start).
    short = dataclasses.replace(config, steps=10)
    first, again = (fit_field(views, short, key=jax.random.key(0), progress=False) for _ in range(2))
    assert isinstance(again.field, GridField) and isinstance(first.field, GridField)
    np.testing.assert_array_equal(np.asarray(again.field.density), np.asarray(first.field.density))
    assert not np.array_equal(np.asarray(first.field.density), np.asarray(result.field.density))


def test_fit_refuses_bad_settings_and_views_without_masks(tmp_path):
    render_views(BOX, tmp_path / "views", n_views=4, resolution=16, progress=False)
    views = load_nerf_synthetic(tmp_path / "views")
    with pytest.raises(FitError, match="model must be"):
        fit_field(views, FitConfig(steps=1, model="octree"), key=jax.random.key(0), progress=False)
    with pytest.raises(FitError, match="n_samples"):
        fit_field(views, FitConfig(steps=1, n_samples=1), key=jax.random.key(0), progress=False)
    bare = type(views)(views.images, None, views.cameras, views.files)
    with pytest.raises(FitError, match="no masks"):
        fit_field(bare, FitConfig(steps=1), key=jax.random.key(0), progress=False)


@pytest.mark.slow
@pytest.mark.optimized
def test_the_bunny_fitted_from_50_views_gives_the_mesh_dano(tmp_path, bunny_mesh):
    """Issue acceptance: centre of mass within 2 % of the box diagonal, principal moments within 5 %."""
    render_views(bunny_mesh, tmp_path / "bunny", n_views=50, resolution=64, progress=False)
    views = load_nerf_synthetic(tmp_path / "bunny")
    result = fit_field(views, FitConfig(steps=300), key=jax.random.key(0), progress=False)  # 0.3 % and 2.1 % measured
    assert isinstance(result.field, GridField)
    solid = solidify(result.field, views)
    d = dano.build_dano(solid.field, n_points=3000, mass=1.0)
    diagonal = np.linalg.norm(np.ptp(bunny_mesh.vertices, axis=0))
    assert np.linalg.norm(np.asarray(d.com) - bunny_mesh.center_mass) < 0.02 * diagonal
    np.testing.assert_allclose(np.asarray(d.principal_moments()), _principal_per_mass(bunny_mesh), rtol=0.05)


def _slide_and_turn(mesh, n):
    t = np.linspace(0.0, 1.0, n)
    pos = np.stack([0.1 * t, 0.02 * np.sin(3 * t), np.full(n, -mesh.bounds[0, 2])], axis=1)
    yaw = np.radians(60.0) * t
    quat = np.asarray(quat_exp(jnp.asarray(np.stack([0 * yaw, 0 * yaw, yaw], axis=1))))
    return pos, quat


def _errors(result, pos, quat):
    position = np.linalg.norm(result.positions - pos, axis=1)
    angle = np.degrees(2 * np.arccos(np.clip(np.abs(np.sum(result.quats * quat, axis=1)), 0.0, 1.0)))
    return position, angle


@pytest.fixture(scope="module")
def box_video(tmp_path_factory):
    """The box sliding and turning over 8 frames: true poses, the camera, its 64 x 48 masks."""
    pos, quat = _slide_and_turn(BOX, 8)
    camera = camera_from_fov(64, 48, np.radians(50.0), look_at([0.05, -0.2, 0.12], [0.05, 0.0, 0.02]))
    folder = tmp_path_factory.mktemp("box") / "video"
    render_mesh_video(BOX, np.concatenate([pos, quat], axis=1), camera, folder, floor=True, progress=False)
    return pos, quat, camera, load_masks(folder / "masks", 8, (48, 64))


@pytest.mark.optimized
def test_tracking_a_rendered_box_sliding_and_turning(box_video):
    pos, quat, camera, masks = box_video
    field = mesh_field(BOX, resolution=80, progress=False)
    result = track(field, camera, masks, init=(pos[0], quat[0]), progress=False)
    position, angle = _errors(result, pos, quat)
    size = np.linalg.norm([0.08, 0.05, 0.04])
    assert position.mean() < 0.02 * size and angle.mean() < 3.0  # the acceptance
    assert result.losses.max() < 0.02


@pytest.mark.optimized
def test_refine_pulls_noisy_poses_back_onto_the_masks(box_video):
    pos, quat, camera, masks = box_video
    config = TrackConfig(refine_iterations=80)
    s = silhouette(mesh_field(BOX, resolution=80, progress=False), camera, config)
    size, corners = windows(masks)
    rays, targets = crop(s, masks, size, corners)
    noisy = pos + np.random.default_rng(0).normal(scale=0.004, size=pos.shape)
    refined, quats = refine(s, rays, jnp.asarray(noisy), jnp.asarray(quat), targets, config)
    before = np.linalg.norm(noisy - pos, axis=1).mean()
    after = np.linalg.norm(np.asarray(refined) - pos, axis=1).mean()
    assert after < 0.5 * before, (after, before)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(quats), axis=1), 1.0, atol=1e-12)


def test_windows_frame_every_mask_with_one_size():
    masks = np.zeros((2, 40, 50))
    masks[0, 5:15, 2:12] = 1.0  # 10 x 10 near the top-left corner
    masks[1, 20:28, 30:44] = 1.0  # 8 x 14
    (height, width), corners = windows(masks, margin=0.25)
    assert (height, width) == (18, 22)  # the largest box, 10 x 14, grown by 4 px on each side
    for mask, (top, left) in zip(masks, corners, strict=True):
        assert 0 <= top <= 40 - height and 0 <= left <= 50 - width
        assert mask[top : top + height, left : left + width].sum() == mask.sum()
    assert tuple(corners[1]) == (20 + 4 - 9, 30 + 7 - 11)  # centred on the box


def test_silhouette_loss_gradient_matches_central_differences():
    camera = camera_from_fov(24, 18, np.radians(50.0), look_at([0.0, -0.3, 0.15], [0.0, 0.0, 0.02]))
    field = mesh_field(BOX, resolution=24, progress=False)
    s = silhouette(field, camera, TrackConfig(n_samples=32, grid=24))
    target = render_silhouette(s, jnp.asarray([0.0, 0.0, 0.02]), jnp.asarray([1.0, 0.0, 0.0, 0.0]))

    def loss(p):
        return mask_loss(s, render_silhouette(s, p[:3], quat_exp(p[3:])), target, 1.0)

    p = jnp.asarray([0.006, -0.004, 0.025, 0.05, -0.03, 0.1])
    g = jax.grad(loss)(p)
    h = 1e-6
    fd = np.array([(loss(p.at[i].add(h)) - loss(p.at[i].add(-h))) / (2 * h) for i in range(6)])
    np.testing.assert_allclose(g, fd, rtol=1e-4, atol=1e-6 * np.abs(fd).max())
    assert np.abs(fd).max() > 1e-3


def test_track_refuses_masks_of_another_size_and_empty_masks():
    camera = camera_from_fov(16, 12, np.radians(50.0), look_at([0.0, -0.3, 0.1], [0.0, 0.0, 0.0]))
    field = mesh_field(BOX, resolution=16, progress=False)
    with pytest.raises(TrackError, match=r"\(12, 16\)"):
        track(field, camera, np.ones((2, 10, 16)), progress=False)
    masks = np.ones((3, 12, 16))
    masks[1] = 0.0
    with pytest.raises(TrackError, match="frame 1 is empty"):
        track(field, camera, masks, progress=False)
    small, cam = downsample(np.ones((1, 12, 16)), camera, 2)
    assert small.shape == (1, 6, 8) and cam.fx == pytest.approx(camera.fx / 2)


def test_each_fitting_back_end_holds_its_own_settings_behind_one_interface():
    from dano.vision.fit import AbstractRadiance, MlpModel, init_radiance_field

    assert FitConfig("mlp").model == MlpModel() and FitConfig().model == GridModel()
    with pytest.raises(FitError, match="model must be one of 'grid', 'mlp'"):
        FitConfig(model="octree")
    bounds = np.array([[-0.1, -0.05, -0.02], [0.1, 0.05, 0.02]])
    for model in (GridModel(resolution=16), MlpModel(width=8, depth=1, n_frequencies=2)):
        field = init_radiance_field(bounds, FitConfig(model, n_samples=16), key=jax.random.key(0))
        assert isinstance(field, AbstractRadiance)
        sigma, colour = field(jnp.zeros((5, 3)))
        assert sigma.shape == (5,) and colour.shape == (5, 3) and np.all(np.asarray(sigma) > 0)
    assert GridModel().regularisation == 1e-4 and MlpModel().regularisation == 0.0


def test_every_solver_reports_in_one_shape(tmp_path):
    """fit_field, track, identify and iLQR return an `AbstractSolution`: the value found, how it
    stopped and why, its stats. A fit whose loss becomes non-finite stops there: reported with the
    last finite model (`throw=False`) or raised (`throw=True`, the default for a fit)."""
    from dano.results import AbstractSolution, Result, SolverError
    from dano.sysid.solve import Identification
    from dano.trajopt.ilqr import Solution
    from dano.vision.fit import FitResult
    from dano.vision.track import TrackResult

    for cls in (FitResult, TrackResult, Identification, Solution):
        assert issubclass(cls, AbstractSolution)
    render_views(BOX, tmp_path / "views", n_views=4, resolution=16, progress=False)
    views = load_nerf_synthetic(tmp_path / "views")
    fine = fit_field(views, FitConfig(steps=3, n_samples=8), key=jax.random.key(0), progress=False)
    assert fine.result is Result.completed and fine.result.ok and not fine.converged
    assert fine.value is fine.field and fine.stats["iterations"] == 3 == len(fine.loss)
    wild = FitConfig(steps=30, n_samples=8, learning_rate=1e30)
    bad = fit_field(views, wild, key=jax.random.key(0), progress=False, throw=False)
    assert bad.result is Result.nonfinite and "lower the learning rate" in bad.message
    assert bad.iterations < 30 and np.all(np.isfinite(bad.loss))
    assert isinstance(bad.field, GridField) and np.all(np.isfinite(np.asarray(bad.field.density)))
    with pytest.raises(SolverError, match="^fit_field failed: the loss became non-finite: stopped at step 1"):
        fit_field(views, wild, key=jax.random.key(0), progress=False)


def test_solidify_carves_a_box_out_of_the_space_its_cameras_see(tmp_path):
    """A box's own field (no fit) seen from 8 cameras around it: every node more than a cell and a
    half inside the box is solid, every node as far outside is carved away (each camera looks only
    at the nodes the ones before it have not seen: a wrong index there shows as a hole or a speck)."""
    render_views(BOX, tmp_path / "views", n_views=8, resolution=16, progress=False)
    views = load_nerf_synthetic(tmp_path / "views")
    field = mesh_field(BOX, resolution=24, progress=False)
    solid = solidify(field, views)
    nx, ny, nz = field.density.shape
    nodes = grid_nodes(field.bounds, (nx, ny, nz)).reshape(-1, 3)
    margin = 1.5 * float(np.max(field.spacing))
    depth = np.min(np.asarray([0.04, 0.025, 0.02]) - np.abs(nodes), axis=1)  # > 0 inside, distance to a face
    solid_nodes = np.asarray(solid.field.density).reshape(-1) > 0
    assert solid_nodes[depth > margin].all() and not solid_nodes[depth < -margin].any()
    assert (solid.seen.reshape(-1)[depth > margin] <= 0.8).all()
    assert depth[depth > margin].size > 50 and depth[depth < -margin].size > 1000
