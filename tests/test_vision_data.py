"""Cameras, NeRF-style datasets, MuJoCo-rendered ground truth, videos and masks (`dano.vision`)."""

import json
import math
import re

import imageio.v3 as iio
import numpy as np
import pytest
import trimesh
from scipy.spatial import ConvexHull
from scipy.spatial.transform import Rotation

from dano import vision as vd
from dano.sysid import read_tracks
from dano.vision import VisionDataError

RES = 32
N_VIEWS = 4
FOV_DEG = 40.0
RGBA = (0.8, 0.6, 0.4, 1.0)
GREY = (0.5, 0.5, 0.5)
RASTER_TOLERANCE = 0.02
"""px: GL covers a pixel whose centre is inside a triangle, computed in float32; pixels that differ
from our exact projection lie on the silhouette's edge, within rounding of it."""


def _camera(seed: int, width: int = 40, height: int = 30) -> vd.Camera:
    """A general camera: fx != fy, off-centre principal point, random pose."""
    rng = np.random.default_rng(seed)
    c2w = np.eye(4)
    c2w[:3, :3] = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    c2w[:3, 3] = rng.normal(size=3)
    return vd.Camera(width, height, 35.0 + rng.uniform(), 33.0 + rng.uniform(), 21.3, 14.2, c2w)


def _box() -> trimesh.Trimesh:
    """A convex box away from the origin and rotated: MuJoCo recentres meshes, this checks it undoes that."""
    mesh = trimesh.creation.box((0.1, 0.06, 0.03))
    mesh.apply_transform(trimesh.transformations.rotation_matrix(0.4, (1.0, 2.0, 0.5)))
    mesh.apply_translation((0.3, -0.1, 0.05))
    return mesh


def _silhouette(uv: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Which pixel centres lie inside the convex hull of `uv`, and their distance to its boundary (px)."""
    hull = uv[ConvexHull(uv).vertices]  # counter-clockwise in (u, v)
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    p = np.stack([u, v], axis=-1)[:, :, None, :]
    a, b = hull, np.roll(hull, -1, axis=0)
    edge = b - a
    cross = edge[:, 0] * (p[..., 1] - a[:, 1]) - edge[:, 1] * (p[..., 0] - a[:, 0])
    inside = np.all(cross >= 0, axis=-1)
    s = np.clip(np.sum((p - a) * edge, axis=-1) / np.sum(edge * edge, axis=-1), 0.0, 1.0)
    distance = np.min(np.linalg.norm(p - (a + s[..., None] * edge), axis=-1), axis=-1)
    return inside, distance


def _assert_mask_is_projection(mask: np.ndarray, camera: vd.Camera, vertices: np.ndarray) -> None:
    """MuJoCo's segmentation equals the convex mesh's projection through `project`, up to GL rounding."""
    uv, depth = vd.project(camera, vertices)
    assert np.all(depth > 0)
    inside, distance = _silhouette(uv, camera.height, camera.width)
    differ = (mask > 0.5) != inside
    assert np.all(distance[differ] < RASTER_TOLERANCE), (
        f"{differ.sum()} pixels differ, up to {distance[differ].max()} px"
    )
    rows, cols = np.nonzero(mask > 0.5)
    np.testing.assert_allclose([cols.min(), rows.min()], uv.min(axis=0), atol=1.0)
    np.testing.assert_allclose([cols.max() + 1, rows.max() + 1], uv.max(axis=0), atol=1.0)


@pytest.fixture(scope="module")
def views_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("views") / "box"
    return vd.render_views(_box(), out, n_views=N_VIEWS, resolution=RES, fov_x_deg=FOV_DEG, seed=3, progress=False)


# --- cameras


def test_camera_json_round_trip(tmp_path):
    camera = _camera(0)
    vd.save_camera(tmp_path / "camera.json", camera)
    loaded = vd.load_camera(tmp_path / "camera.json")
    for name in ("width", "height", "fx", "fy", "cx", "cy"):
        assert getattr(loaded, name) == getattr(camera, name)
    np.testing.assert_array_equal(loaded.c2w, camera.c2w)


@pytest.mark.parametrize("seed", [0, 1])
def test_project_inverts_camera_rays(seed):
    camera = _camera(seed)
    origins, directions = vd.camera_rays(camera)
    assert origins.shape == directions.shape == (camera.height * camera.width, 3)
    np.testing.assert_allclose(np.linalg.norm(directions, axis=1), 1.0, rtol=1e-12)
    t = np.random.default_rng(seed).uniform(0.1, 5.0, size=len(directions))
    uv, depth = vd.project(camera, origins + t[:, None] * directions)
    v, u = np.divmod(np.arange(len(uv)), camera.width)  # row-major: index = v * width + u
    np.testing.assert_allclose(uv, np.stack([u + 0.5, v + 0.5], axis=1), atol=1e-9)
    np.testing.assert_allclose(depth, t * (directions @ -camera.c2w[:3, 2]), rtol=1e-12)


def test_look_at_and_field_of_view():
    fov = math.radians(50.0)
    camera = vd.camera_from_fov(64, 48, fov, vd.look_at((1.0, 2.0, 0.5), (0.0, 0.0, 0.5)))
    np.testing.assert_allclose(camera.position, (1.0, 2.0, 0.5))
    target_uv, depth = vd.project(camera, np.array([[0.0, 0.0, 0.5], [0.0, 0.0, 0.6]]))
    np.testing.assert_allclose(target_uv[0], (32.0, 24.0), atol=1e-12)  # the target at the principal point
    assert target_uv[1, 1] < target_uv[0, 1]  # world up is image up (v decreases)
    np.testing.assert_allclose(depth[0], math.sqrt(5.0))
    # a ray at half the horizontal field of view off the axis lands on the image's left edge
    local = np.array([-math.tan(fov / 2), 0.0, -1.0])
    edge = camera.position + camera.c2w[:3, :3] @ local
    np.testing.assert_allclose(vd.project(camera, edge[None])[0][0], (0.0, 24.0), atol=1e-9)
    pole = vd.look_at((0.0, 0.0, 2.0), (0.0, 0.0, 0.0))  # looking along up: another axis serves as up
    np.testing.assert_allclose(pole[:3, :3].T @ pole[:3, :3], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(pole[:3, 2], (0.0, 0.0, 1.0))


def _write_camera(path, **changes):
    record = {"width": 40, "height": 30, "fx": 35.0, "fy": 35.0, "cx": 20.0, "cy": 15.0, "c2w": np.eye(4).tolist()}
    record.update(changes)
    for key in [k for k, v in changes.items() if v is None]:
        del record[key]
    path.write_text(json.dumps(record))
    return path


def _rotated(angle: float, scale: float = 1.0):
    c2w = np.eye(4)
    c2w[:3, :3] = scale * Rotation.from_rotvec([0.0, 0.0, angle]).as_matrix()
    return c2w.tolist()


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"fx": None}, r"missing key\(s\) \['fx'\]"),
        ({"width": 0}, "'width' must be a positive integer"),
        ({"fy": -1.0}, "'fy' must be positive"),
        ({"c2w": np.eye(4)[:3].tolist()}, r"must be 4 x 4, got shape \(3, 4\)"),
        ({"c2w": [[1, 2], [3]]}, "must be a 4 x 4 list of numbers"),
        ({"c2w": [[float("nan")] * 4] * 4}, "NaN or infinite"),
        ({"c2w": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]]}, "bottom row must be 0, 0, 0, 1"),
        ({"c2w": _rotated(0.3, scale=1.001)}, "not orthonormal"),
        ({"c2w": np.diag([1.0, 1.0, -1.0, 1.0]).tolist()}, "right-handed"),
    ],
)
def test_load_camera_rejects_bad_files(tmp_path, changes, message):
    path = _write_camera(tmp_path / "cam.json", **changes)
    with pytest.raises(VisionDataError, match=f"cam.json.*{message}"):
        vd.load_camera(path)


def test_load_camera_missing_or_not_json(tmp_path):
    with pytest.raises(VisionDataError, match="nothere.json: no such file"):
        vd.load_camera(tmp_path / "nothere.json")
    (tmp_path / "bad.json").write_text("{width: 3")
    with pytest.raises(VisionDataError, match="bad.json: not readable JSON"):
        vd.load_camera(tmp_path / "bad.json")


# --- rendered multi-view datasets


def test_render_views_round_trip(views_dir):
    views = vd.load_nerf_synthetic(views_dir)
    assert views.images.shape == (N_VIEWS, RES, RES, 3) and views.images.dtype == np.float32
    assert views.masks is not None and views.masks.shape == (N_VIEWS, RES, RES)
    assert [f.split("/")[-2:] for f in views.files] == [["images", f"r_{k:03d}.png"] for k in range(N_VIEWS)]
    fov = math.radians(FOV_DEG)
    centre, radius = vd.bounding_sphere(_box())
    expected = vd.sphere_cameras(centre, vd.framing_distance(radius, fov), N_VIEWS, RES, fov, seed=3)
    for camera, truth in zip(views.cameras, expected, strict=True):
        np.testing.assert_array_equal(camera.c2w, truth.c2w)
        assert (camera.width, camera.height, camera.cx, camera.cy) == (RES, RES, RES / 2, RES / 2)
        assert camera.fx == pytest.approx(truth.fx, rel=1e-14) and camera.fy == camera.fx
    for k, mask in enumerate(views.masks):
        np.testing.assert_array_equal(mask, iio.imread(views_dir / "masks" / f"r_{k:03d}.png") / 255.0)
        assert set(np.unique(mask)) == {0.0, 1.0}
        assert 0.05 < mask.mean() < 0.6  # framed with a margin, not clipped
    outside = views.masks == 0
    np.testing.assert_array_equal(views.images[outside], 1.0)  # composited onto white
    colour = views.images[~outside] / np.array(RGBA[:3], dtype=np.float32)
    assert 0.55 < colour.min() and colour.max() < 0.95  # the shading range of the fixed lights


def test_rendered_mask_is_the_projected_mesh(views_dir):
    views = vd.load_nerf_synthetic(views_dir)
    assert views.masks is not None
    for mask, camera in zip(views.masks, views.cameras, strict=True):
        _assert_mask_is_projection(mask, camera, np.asarray(_box().vertices))


def test_downscale_box_averages(views_dir):
    full = vd.load_nerf_synthetic(views_dir, background=(0.0, 0.0, 1.0))
    half = vd.load_nerf_synthetic(views_dir, downscale=2, background=(0.0, 0.0, 1.0))
    assert half.images.shape == (N_VIEWS, RES // 2, RES // 2, 3) and full.masks is not None and half.masks is not None
    blocks = full.images.reshape(N_VIEWS, RES // 2, 2, RES // 2, 2, 3).mean(axis=(2, 4))
    np.testing.assert_allclose(half.images, blocks, atol=1e-6)
    np.testing.assert_allclose(half.masks, full.masks.reshape(N_VIEWS, RES // 2, 2, RES // 2, 2).mean(axis=(2, 4)))
    for a, b in zip(full.cameras, half.cameras, strict=True):
        assert (b.width, b.fx, b.cx) == (a.width // 2, a.fx / 2, a.cx / 2)
        np.testing.assert_array_equal(a.c2w, b.c2w)
    assert np.all(full.images[full.masks == 0] == np.array([0.0, 0.0, 1.0], dtype=np.float32))


def test_render_views_refuses_to_overwrite(views_dir):
    with pytest.raises(VisionDataError, match=f"{re.escape(str(views_dir))}: already exists"):
        vd.render_views(_box(), views_dir, n_views=2, resolution=8, progress=False)


# --- rendered videos


def _poses(n: int) -> np.ndarray:
    angle = np.linspace(0.0, 1.2, n)
    quat = Rotation.from_rotvec(angle[:, None] * np.array([0.3, 0.2, 1.0])).as_quat()[:, [3, 0, 1, 2]]
    pos = np.stack([np.linspace(-0.05, 0.08, n), 0.03 * angle, np.full(n, 0.04)], axis=1)
    return np.concatenate([pos, 2.0 * quat], axis=1)  # quaternions need not be unit


def test_render_video_round_trip(tmp_path):
    mesh = trimesh.creation.icosphere(subdivisions=1, radius=0.03)
    mesh.apply_translation((0.01, 0.0, 0.0))
    camera = vd.camera_from_fov(48, 32, math.radians(50.0), vd.look_at((0.25, -0.2, 0.2), (0.0, 0.0, 0.03)))
    poses = _poses(4)
    out = vd.render_mesh_video(mesh, poses, camera, tmp_path / "video", background=GREY, fps=25.0, progress=False)
    frames, files = vd.load_frames(out / "frames")
    assert frames.shape == (4, 32, 48, 3) and [f.split("/")[-1] for f in files] == [f"{k:06d}.png" for k in range(4)]
    masks = vd.load_masks(out / "masks", 4, (32, 48))
    track = read_tracks(out / "poses.csv")[""]
    np.testing.assert_allclose(track.t, np.arange(4) / 25.0, atol=1e-12)
    np.testing.assert_allclose(
        np.concatenate([track.pos, track.quat], axis=1), poses / [1, 1, 1, 2, 2, 2, 2], atol=1e-11
    )
    loaded = vd.load_camera(out / "camera.json")
    np.testing.assert_array_equal(loaded.c2w, camera.c2w)
    for mask, frame, p, q in zip(masks, frames, track.pos, track.quat, strict=True):
        R = Rotation.from_quat(q[[1, 2, 3, 0]]).as_matrix()
        _assert_mask_is_projection(mask, camera, np.asarray(mesh.vertices) @ R.T + p)
        np.testing.assert_array_equal(frame[mask == 0], np.float32(128 / 255))  # the plain background
    keyed = vd.colour_key_masks(frames, GREY)
    iou = np.sum(keyed * masks) / np.sum(np.maximum(keyed, masks))
    assert iou > 0.95


def test_render_video_floor_is_not_in_the_mask(tmp_path):
    mesh = trimesh.creation.box((0.04, 0.04, 0.04))
    camera = vd.camera_from_fov(32, 32, math.radians(60.0), vd.look_at((0.2, -0.15, 0.15), (0.0, 0.0, 0.02)))
    poses = np.array([[0.0, 0.0, 0.02, 1.0, 0.0, 0.0, 0.0]] * 3)
    bare = vd.render_mesh_video(mesh, poses, camera, tmp_path / "bare", progress=False)
    floor = vd.render_mesh_video(mesh, poses, camera, tmp_path / "floor", floor=True, progress=False)
    np.testing.assert_array_equal(
        vd.load_masks(bare / "masks", 3, (32, 32)), vd.load_masks(floor / "masks", 3, (32, 32))
    )
    bare_frames, floor_frames = vd.load_frames(bare / "frames")[0], vd.load_frames(floor / "frames")[0]
    assert np.mean(np.any(bare_frames != floor_frames, axis=-1)) > 0.3  # the floor covers the background


def test_render_video_rejects_other_intrinsics_and_leaves_nothing(tmp_path):
    camera = _camera(0, width=32, height=32)
    with pytest.raises(VisionDataError, match="square pixels"):
        vd.render_mesh_video(trimesh.creation.box((0.1, 0.1, 0.1)), _poses(3), camera, tmp_path / "out", progress=False)
    assert list(tmp_path.iterdir()) == []  # no half-written folder, no temporary one


def test_load_frames_from_video(tmp_path):
    rng = np.random.default_rng(0)
    frames = np.repeat(np.repeat(rng.integers(0, 255, size=(5, 4, 6, 3), dtype=np.uint8), 8, axis=1), 8, axis=2)
    iio.imwrite(tmp_path / "clip.mp4", frames, fps=10, codec="libx264", plugin="pyav")
    loaded, files = vd.load_frames(tmp_path / "clip.mp4")
    assert loaded.shape == (5, 32, 48, 3) and files[1].endswith("clip.mp4#000001")
    assert np.median(np.abs(loaded - frames / 255.0)) < 0.05  # lossy video coding


# --- bad inputs


def _png(path, array):
    path.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(path, np.asarray(array, dtype=np.uint8))


def _dataset(root, n=2, size=(8, 10), **frame_changes):
    """A hand-written NeRF-synthetic dataset: RGBA images, file paths without extension."""
    for k in range(n):
        rgba = np.zeros((*size, 4), np.uint8)
        rgba[2:6, 3:7] = (200, 100, 50, 255)
        _png(root / "train" / f"r_{k}.png", rgba)
    frames = [{"file_path": f"./train/r_{k}", "transform_matrix": np.eye(4).tolist()} for k in range(n)]
    frames[-1].update(frame_changes)
    (root / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 0.7, "frames": frames}))
    return root


def test_load_nerf_synthetic_formats(tmp_path):
    views = vd.load_nerf_synthetic(_dataset(tmp_path / "a"), background=(0.0, 1.0, 0.0))
    assert views.images.shape == (2, 8, 10, 3) and views.masks is not None
    np.testing.assert_allclose(views.images[0, 0, 0], (0.0, 1.0, 0.0))
    np.testing.assert_allclose(views.images[0, 3, 4], np.array([200, 100, 50]) / 255, rtol=1e-6)
    assert views.cameras[0].fx == pytest.approx(5.0 / math.tan(0.35))
    # instant-ngp intrinsics with a per-frame override, RGB images with masks in masks/
    root = tmp_path / "b"
    for k in range(2):
        _png(root / "images" / f"f{k}.jpg", np.full((8, 10, 3), 90))
        _png(root / "masks" / f"f{k}.png", np.pad(np.full((2, 2), 255), ((3, 3), (4, 4))))
    frames = [{"file_path": f"images/f{k}.jpg", "transform_matrix": np.eye(4).tolist()} for k in range(2)]
    frames[1]["fl_x"] = 12.0
    meta = {"fl_x": 9.0, "fl_y": 9.5, "cx": 4.5, "cy": 4.0, "w": 10, "h": 8, "frames": frames}
    (root / "transforms.json").write_text(json.dumps(meta))
    views = vd.load_nerf_synthetic(root)
    assert [(c.fx, c.fy, c.cx, c.cy) for c in views.cameras] == [(9.0, 9.5, 4.5, 4.0), (12.0, 9.5, 4.5, 4.0)]
    assert views.masks is not None and views.masks.sum(axis=(1, 2)).tolist() == [4.0, 4.0]


def _empty_mask(root):
    _png(root / "masks" / "r_1.png", np.zeros((8, 10)))
    return root


def _small_mask(root):
    _png(root / "masks" / "r_1.png", np.full((4, 5), 255))
    return root


def _missing_image(root):
    (root / "train" / "r_1.png").unlink()
    return root


def _other_size(root):
    _png(root / "train" / "r_1.png", np.zeros((8, 12, 4)))
    return root


@pytest.mark.parametrize(
    ("make", "file", "message"),
    [
        (lambda r: r, "transforms_val.json", "no such file"),
        (lambda r: _dataset(r, transform_matrix=np.eye(4)[:3].tolist()), "transforms_train.json", "frame 1.*4 x 4"),
        (lambda r: _dataset(r, transform_matrix=[[float("inf")] * 4] * 4), "transforms_train.json", "frame 1.*NaN"),
        (lambda r: _missing_image(_dataset(r)), "r_1", "image not found"),
        (lambda r: _other_size(_dataset(r)), "r_1.png", "size 12x8 differs"),
        (lambda r: _small_mask(_dataset(r)), "masks/r_1.png", "mask is 5x4, its image 10x8"),
        (lambda r: _empty_mask(_dataset(r)), "masks/r_1.png", "empty mask"),
        (lambda r: _dataset(r, camera_angle_x="wide"), "transforms_train.json", "'camera_angle_x' must be a finite"),
    ],
)
def test_load_nerf_synthetic_rejects_bad_inputs(tmp_path, make, file, message):
    root = make(tmp_path / "data")
    split = "val" if file == "transforms_val.json" else "train"
    with pytest.raises(VisionDataError, match=f"{re.escape(file)}.*{message}"):
        vd.load_nerf_synthetic(root, split=split)


def test_load_masks_and_frames_reject_bad_inputs(tmp_path):
    for k in range(3):
        _png(tmp_path / "masks" / f"{k:06d}.png", np.pad(np.full((2, 2), 255), 3))
    with pytest.raises(VisionDataError, match=r"masks: 3 masks for 5 frames: no mask for frame 3 and after"):
        vd.load_masks(tmp_path / "masks", 5, (8, 8))
    with pytest.raises(VisionDataError, match=r"000002.png: 3 masks for 2 frames; this one is extra"):
        vd.load_masks(tmp_path / "masks", 2, (8, 8))
    with pytest.raises(VisionDataError, match=r"000000.png: mask is 8x8, its image 9x8"):
        vd.load_masks(tmp_path / "masks", 3, (8, 9))
    _png(tmp_path / "masks" / "000001.png", np.zeros((8, 8)))
    with pytest.raises(VisionDataError, match=r"000001.png: empty mask"):
        vd.load_masks(tmp_path / "masks", 3, (8, 8))
    with pytest.raises(VisionDataError, match=r"nothing: no such file or folder"):
        vd.load_frames(tmp_path / "nothing")
    _png(tmp_path / "frames" / "a.png", np.zeros((8, 8, 3)))
    _png(tmp_path / "frames" / "b.png", np.zeros((8, 6, 3)))
    with pytest.raises(VisionDataError, match=r"b.png: size 6x8 differs from .*a.png's 8x8"):
        vd.load_frames(tmp_path / "frames")
    (tmp_path / "clip.mp4").write_text("not a video")
    with pytest.raises(VisionDataError, match=r"clip.mp4: not a readable video"):
        vd.load_frames(tmp_path / "clip.mp4")
