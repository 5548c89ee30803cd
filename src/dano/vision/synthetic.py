"""Ground truth rendered with MuJoCo: posed views of a mesh for fitting (`render_views`, in the
NeRF-synthetic layout) and a mesh moving before a fixed camera for tracking (`render_mesh_video`:
`frames/000000.png`, ..., `masks/`, `camera.json` and the true poses `poses.csv`
(`t,x,y,z,qw,qx,qy,qz`, read by `dano.sysid.read_tracks`)). Folders appear complete or not at all.
"""

import json
import math
from collections.abc import Sequence
from pathlib import Path

import imageio.v3 as iio
import mujoco
import numpy as np
import trimesh
from jaxtyping import Float
from tqdm.auto import tqdm

from dano.errors import MeshError
from dano.io import atomic_folder
from dano.sim.render import make_renderer
from dano.sysid.data import Track, write_track
from dano.vision.camera import Camera, MatrixLike, VectorLike, VisionDataError, camera_from_fov, look_at, save_camera

_LIGHTS = (  # (direction the light travels, diffuse): a key light from above and three fills
    ((-0.3, -0.5, -1.0), 0.4),
    ((0.8, 0.4, 0.3), 0.2),
    ((-0.5, 0.8, 0.2), 0.2),
    ((0.2, -0.6, 0.8), 0.2),
)
_AMBIENT = 0.5
"""Every surface gets 0.6-0.9 of its colour whatever its normal; no specular, so no view dependence."""


def sphere_cameras(
    centre: VectorLike, distance: float, n_views: int, resolution: int, fov_x: float, seed: int = 0
) -> tuple[Camera, ...]:
    """Square cameras on a sphere around `centre`, looking at it, z up.

    Directions are a golden-spiral (Fibonacci) set covering the sphere evenly, rotated by a
    rotation drawn from `seed`, so different seeds give different but equally even views.

    Args:
        centre: (3,) world frame, m.
        distance: from `centre`, m.
        resolution: image width and height, pixels.
        fov_x: horizontal (= vertical) field of view, rad.
    """
    i = np.arange(n_views) + 0.5
    z = 1.0 - 2.0 * i / n_views
    phi = np.pi * (3.0 - np.sqrt(5.0)) * i
    r = np.sqrt(1.0 - z * z)
    directions = np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)
    q = np.random.default_rng(seed).normal(size=4)
    R = np.zeros(9)
    mujoco.mju_quat2Mat(R, q / np.linalg.norm(q))
    centre = np.asarray(centre, dtype=np.float64)
    eyes = centre + distance * directions @ R.reshape(3, 3).T
    return tuple(camera_from_fov(resolution, resolution, fov_x, look_at(eye, centre)) for eye in eyes)


def framing_distance(radius: float, fov: float, margin: float = 0.1) -> float:
    """The distance, m, at which a sphere of `radius` (m) fills a field of view `fov` (rad) but a margin.

    The sphere's angular radius asin(radius / distance) is then asin(sin(fov / 2) / (1 + margin)).
    """
    return (1.0 + margin) * radius / math.sin(0.5 * fov)


def bounding_sphere(mesh: trimesh.Trimesh) -> tuple[Float[np.ndarray, "3"], float]:
    """The centre of the mesh's axis-aligned bounding box and the largest vertex distance from it, m."""
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    centre = 0.5 * (vertices.min(axis=0) + vertices.max(axis=0))
    return centre, float(np.max(np.linalg.norm(vertices - centre, axis=1)))


def render_views(
    mesh: trimesh.Trimesh,
    out_dir: str | Path,
    n_views: int = 50,
    resolution: int = 64,
    fov_x_deg: float = 40.0,
    distance: float | None = None,
    seed: int = 0,
    rgba: VectorLike = (0.8, 0.6, 0.4, 1.0),
    overwrite: bool = False,
    progress: bool = True,
) -> Path:
    """Renders a mesh from around it into a NeRF-synthetic dataset folder (read by `load_nerf_synthetic`).

    Writes `transforms.json` (`camera_angle_x`, frames with `file_path` "images/r_000.png" and
    `transform_matrix`), RGBA PNGs `images/r_000.png` whose alpha is the object's exact mask
    (MuJoCo's segmentation render), and the same masks as `masks/r_000.png` (0 or 255). Cameras
    come from `sphere_cameras` around the mesh's bounding-box centre. Lighting is fixed directional
    light without specular highlights, so a surface point looks the same from every view. The
    folder appears complete or not at all (written beside it, then renamed).

    Args:
        mesh: in world coordinates, m.
        out_dir: the dataset folder to create.
        n_views: number of images.
        resolution: image width and height, pixels.
        fov_x_deg: field of view, degrees.
        distance: camera distance from the centre, m; default `framing_distance` of the bounding sphere.
        seed: rotates the camera directions.
        rgba: the object's colour, each in [0, 1].
        overwrite: replace `out_dir` if it exists (else raise `VisionDataError`).
        progress: show a progress bar.

    Example:
        >>> render_views(trimesh.creation.icosphere(radius=0.05), "ball_views", n_views=20)
        >>> views = load_nerf_synthetic("ball_views")
    """
    if n_views < 1 or resolution < 1 or not 0.0 < fov_x_deg < 180.0:
        raise ValueError(f"render_views: need n_views, resolution >= 1 and 0 < fov_x_deg < 180, got "
                         f"{n_views}, {resolution}, {fov_x_deg}")  # fmt: skip
    fov = math.radians(fov_x_deg)
    centre, radius = bounding_sphere(mesh)
    distance = framing_distance(radius, fov) if distance is None else float(distance)
    cameras = sphere_cameras(centre, distance, n_views, resolution, fov, seed)
    digits = max(3, len(str(n_views - 1)))
    names = [f"r_{k:0{digits}d}.png" for k in range(n_views)]
    with _new_folder(out_dir, overwrite) as tmp, _MeshRenderer(mesh, rgba, cameras[0], None) as renderer:
        (tmp / "images").mkdir()
        (tmp / "masks").mkdir()
        renderer.set_depth_range(cameras, centre[None], radius)
        for camera, name in zip(tqdm(cameras, desc="views", disable=not progress, unit="view"), names, strict=True):
            colour, mask, _ = renderer.render(camera, np.eye(4))
            iio.imwrite(
                tmp / "images" / name, np.concatenate([colour, 255 * mask[:, :, None].astype(np.uint8)], axis=2)
            )
            iio.imwrite(tmp / "masks" / name, 255 * mask.astype(np.uint8))
        frames = [
            {"file_path": f"images/{n}", "transform_matrix": c.c2w.tolist()}
            for n, c in zip(names, cameras, strict=True)
        ]
        (tmp / "transforms.json").write_text(json.dumps({"camera_angle_x": fov, "frames": frames}, indent=2) + "\n")
    return Path(out_dir)


def render_mesh_video(
    mesh: trimesh.Trimesh,
    poses: MatrixLike,
    camera: Camera,
    out_dir: str | Path,
    rgba: VectorLike = (0.8, 0.6, 0.4, 1.0),
    background: VectorLike = (0.5, 0.5, 0.5),
    fps: float = 30.0,
    floor: bool = False,
    floor_height: float = 0.0,
    overwrite: bool = False,
    progress: bool = True,
) -> Path:
    """Renders a mesh moving in front of a fixed camera: ground truth for pose tracking.

    Writes `frames/000000.png` (RGB on a plain `background`), `masks/000000.png` (0 or 255, the
    object only, never the floor), `camera.json` (`save_camera`) and `poses.csv` (`t,x,y,z,qw,qx,qy,qz`
    with t = i / fps: the mesh frame's pose). The folder appears complete or not at all.

    Args:
        mesh: in its own frame, m.
        poses: (n, 7) x, y, z, qw, qx, qy, qz of the mesh frame in the world (mesh -> world), m.
        camera: the fixed camera; MuJoCo renders square pixels (fx = fy) with a centred principal point only.
        out_dir: the folder to create.
        rgba: the object's colour.
        background: RGB of everything that is neither object nor floor.
        fps: frames per second, for the t column.
        floor: add a checkered floor plane z = `floor_height` (m, world frame).
        overwrite: replace `out_dir` if it exists (else raise `VisionDataError`).
        progress: show a progress bar.
    """
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 2 or poses.shape[1] != 7 or len(poses) == 0 or not np.all(np.isfinite(poses)):
        raise VisionDataError(f"{out_dir}: poses must be a finite (n, 7) array, got shape {poses.shape}")
    if np.any(np.linalg.norm(poses[:, 3:], axis=1) < 1e-9):
        raise VisionDataError(f"{out_dir}: poses have a zero quaternion")
    if not fps > 0:
        raise VisionDataError(f"{out_dir}: fps must be positive, got {fps}")
    track = Track.from_poses(poses, 1.0 / fps, source=str(out_dir))
    transforms = [_transform(p, q) for p, q in zip(track.pos, track.quat, strict=True)]
    centre, radius = bounding_sphere(mesh)
    centres = np.stack([T[:3, :3] @ centre + T[:3, 3] for T in transforms])
    bg = np.round(255 * np.clip(np.asarray(background, dtype=np.float64).reshape(3), 0, 1)).astype(np.uint8)
    with (
        _new_folder(out_dir, overwrite) as tmp,
        _MeshRenderer(mesh, rgba, camera, floor_height if floor else None) as renderer,
    ):
        (tmp / "frames").mkdir()
        (tmp / "masks").mkdir()
        renderer.set_depth_range([camera], centres, radius)
        for k, T in enumerate(tqdm(transforms, desc="frames", disable=not progress, unit="frame")):
            colour, mask, scene = renderer.render(camera, T)
            iio.imwrite(tmp / "frames" / f"{k:06d}.png", np.where(scene[:, :, None], colour, bg))
            iio.imwrite(tmp / "masks" / f"{k:06d}.png", 255 * mask.astype(np.uint8))
        save_camera(tmp / "camera.json", camera)
        write_track(tmp / "poses.csv", track)
    return Path(out_dir)


def _transform(pos: np.ndarray, quat: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    R = np.zeros(9)
    mujoco.mju_quat2Mat(R, quat)
    T[:3, :3], T[:3, 3] = R.reshape(3, 3), pos
    return T


class _MeshRenderer:
    """MuJoCo's offscreen renderer for one mesh on a mocap body, a camera, lights and maybe a floor.

    A context manager: the GL context is released on exit.
    """

    def __init__(self, mesh: trimesh.Trimesh, rgba: VectorLike, camera: Camera, floor_height: float | None):
        try:
            self.model = _scene_spec(mesh, rgba, camera.width, camera.height, floor_height).compile()
        except ValueError as e:  # MuJoCo's compiler rejects empty or degenerate meshes
            raise MeshError(f"MuJoCo cannot render this mesh: {' '.join(str(e).split())}") from None
        self.data = mujoco.MjData(self.model)
        self.object_id = self.model.geom("object").id
        self.floor_id = self.model.geom("floor").id if floor_height is not None else -2
        self.renderer = make_renderer(self.model, camera.height, camera.width)

    def __enter__(self) -> "_MeshRenderer":
        return self

    def __exit__(self, *exc) -> None:
        self.renderer.close()

    def set_depth_range(self, cameras: Sequence[Camera], centres: np.ndarray, radius: float) -> None:
        """Near and far clipping planes that keep every object position in view (MuJoCo scales them by extent)."""
        distances = np.linalg.norm(np.stack([c.position for c in cameras])[:, None] - centres[None], axis=2)
        near = max(1e-3 * float(distances.max() + radius), 0.5 * float(distances.min() - radius))
        far = 100.0 * float(distances.max() + radius)
        extent = float(self.model.stat.extent)
        self.model.vis.map.znear, self.model.vis.map.zfar = near / extent, far / extent

    def render(self, camera: Camera, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Colour (h, w, 3) uint8, object mask (h, w) bool and object-or-floor mask (h, w) bool.

        Args:
            camera: must have this renderer's size.
            pose: (4, 4) mesh frame -> world.
        """
        _set_camera(self.model, camera)
        self.data.mocap_pos[0] = pose[:3, 3]
        mujoco.mju_mat2Quat(self.data.mocap_quat[0], pose[:3, :3].ravel())
        mujoco.mj_kinematics(self.model, self.data)
        mujoco.mj_camlight(self.model, self.data)
        self.renderer.update_scene(self.data, camera="view")
        self.renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
        colour = self.renderer.render().copy()
        self.renderer.enable_segmentation_rendering()
        try:
            segment = self.renderer.render()
        finally:
            self.renderer.disable_segmentation_rendering()
        is_geom = segment[:, :, 1] == mujoco.mjtObj.mjOBJ_GEOM
        mask = is_geom & (segment[:, :, 0] == self.object_id)
        return colour, mask, mask | (is_geom & (segment[:, :, 0] == self.floor_id))


def _set_camera(model: mujoco.MjModel, camera: Camera) -> None:
    """Points the model's camera "view" like `camera`.

    MuJoCo's camera frame is ours (looks along -z, +y up), so its orientation is c2w's rotation.
    Its intrinsics are only a vertical field of view over the whole image height with the
    principal point at the centre, which is fy = height / (2 tan(fovy / 2)).
    """
    if (
        abs(camera.fx - camera.fy) > 1e-6 * camera.fy
        or max(abs(camera.cx - 0.5 * camera.width), abs(camera.cy - 0.5 * camera.height)) > 1e-6 * camera.width
    ):
        raise VisionDataError(f"MuJoCo renders square pixels about a centred principal point only; got {camera}")
    if (camera.width, camera.height) != (model.vis.global_.offwidth, model.vis.global_.offheight):
        raise ValueError(f"camera size {camera.width}x{camera.height} differs from the renderer's")
    model.cam_pos[0] = camera.position
    mujoco.mju_mat2Quat(model.cam_quat[0], np.ascontiguousarray(camera.rotation).ravel())
    model.cam_fovy[0] = math.degrees(2.0 * math.atan(0.5 * camera.height / camera.fy))


def _scene_spec(
    mesh: trimesh.Trimesh, rgba: VectorLike, width: int, height: int, floor_height: float | None
) -> mujoco.MjSpec:
    """The MuJoCo scene: the mesh on a mocap body, a camera "view", directional lights, maybe a floor."""
    spec = mujoco.MjSpec()
    spec.visual.global_.offwidth, spec.visual.global_.offheight = width, height
    spec.visual.quality.offsamples = 0  # no multisampling: colour edges agree with the segmentation exactly
    spec.visual.headlight.active = 0
    spec.add_material(name="object", rgba=list(np.asarray(rgba, dtype=np.float64).reshape(4)), specular=0.0,
                      shininess=0.0, reflectance=0.0)  # fmt: skip
    spec.add_mesh(name="object", uservert=np.asarray(mesh.vertices, dtype=np.float64).ravel().tolist(),
                  userface=np.asarray(mesh.faces, dtype=np.int64).ravel().tolist(),
                  inertia=mujoco.mjtMeshInertia.mjMESH_INERTIA_SHELL)  # fmt: skip
    body = spec.worldbody.add_body(name="object", mocap=True)
    body.add_geom(name="object", type=mujoco.mjtGeom.mjGEOM_MESH, meshname="object", material="object",
                  contype=0, conaffinity=0)  # fmt: skip
    spec.worldbody.add_camera(name="view")
    for k, (direction, diffuse) in enumerate(_LIGHTS):
        spec.worldbody.add_light(type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL, dir=list(direction),
                                 diffuse=[diffuse] * 3, ambient=[_AMBIENT if k == 0 else 0.0] * 3,
                                 specular=[0.0] * 3, castshadow=False)  # fmt: skip
    if floor_height is not None:
        _add_floor(spec, floor_height, bounding_sphere(mesh)[1])
    return spec


def _add_floor(spec: mujoco.MjSpec, height: float, radius: float) -> None:
    """A checkered plane z = height, tiles about the object's radius, large enough to reach the horizon."""
    spec.add_texture(name="floor", type=mujoco.mjtTexture.mjTEXTURE_2D, builtin=mujoco.mjtBuiltin.mjBUILTIN_CHECKER,
                     rgb1=[0.25, 0.3, 0.35], rgb2=[0.4, 0.45, 0.5], width=64, height=64)  # fmt: skip
    spec.add_material(name="floor", textures=["", "floor"], texrepeat=[0.5 / radius, 0.5 / radius], texuniform=True,
                      specular=0.0, shininess=0.0, reflectance=0.0)  # fmt: skip
    size = [1000.0 * radius, 1000.0 * radius, 1.0]
    spec.worldbody.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, pos=[0.0, 0.0, height], size=size,
                            material="floor", contype=0, conaffinity=0)  # fmt: skip


def _new_folder(out_dir: str | Path, overwrite: bool):
    """`dano.io.atomic_folder`, refusing an existing folder unless `overwrite`."""
    if Path(out_dir).exists() and not overwrite:
        raise VisionDataError(f"{out_dir}: already exists (--overwrite, or overwrite=True, replaces it)")
    return atomic_folder(out_dir)
