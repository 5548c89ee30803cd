"""From pixels: cameras (`camera`), multi-view datasets (`datasets`), images, videos and masks
(`media`), ground truth rendered with MuJoCo (`synthetic`), volume rendering (`render`), fitting a
field to posed images (`fit`), tracking an object's pose in masks (`track`) and identification
from masks end to end (`pixels`).
"""

import warnings

from dano.vision.camera import (
    Camera,
    VisionDataError,
    camera_from_fov,
    camera_rays,
    load_camera,
    look_at,
    project,
    save_camera,
)
from dano.vision.datasets import Views, load_nerf_synthetic
from dano.vision.fit import FitConfig, GridModel, MlpModel, fit_field
from dano.vision.media import box_downscale, colour_key_masks, load_frames, load_masks, read_image, read_mask
from dano.vision.observation import MaskConfig
from dano.vision.pixels import identify_mask_files, identify_masks
from dano.vision.synthetic import bounding_sphere, framing_distance, render_mesh_video, render_views, sphere_cameras
from dano.vision.track import TrackConfig, track


def __getattr__(name: str):
    if name == "render_video":  # renamed in 0.2 (dano.sim.render.render_video renders a simulation); goes in 0.3
        warnings.warn("dano.vision.render_video is now dano.vision.render_mesh_video", DeprecationWarning, stacklevel=2)
        return render_mesh_video
    raise AttributeError(f"module 'dano.vision' has no attribute {name!r}")


__all__ = [
    "Camera", "FitConfig", "GridModel", "MlpModel", "MaskConfig", "TrackConfig", "Views", "VisionDataError",
    "bounding_sphere", "box_downscale", "camera_from_fov", "camera_rays", "colour_key_masks", "fit_field",
    "framing_distance", "identify_mask_files", "identify_masks", "load_camera", "load_frames", "load_masks",
    "load_nerf_synthetic", "look_at", "project", "read_image", "read_mask", "render_mesh_video", "render_views",
    "save_camera", "sphere_cameras", "track",
]  # fmt: skip
