"""From pixels: cameras (`camera`), multi-view datasets (`datasets`), images, videos and masks
(`media`), ground truth rendered with MuJoCo (`synthetic`), volume rendering (`render`), fitting a
field to posed images (`fit`), tracking an object's pose in masks (`track`) and identification
from masks end to end (`pixels`).

Names load on first use (PEP 562): the settings (`configs`) import no JAX, so the command line
reads them to build its options and `dano --help` stays instant.
"""

from typing import TYPE_CHECKING

from dano._lazy import attach

_LAZY = {
    "Camera": "dano.vision.camera",
    "VisionDataError": "dano.vision.camera",
    "camera_from_fov": "dano.vision.camera",
    "camera_rays": "dano.vision.camera",
    "load_camera": "dano.vision.camera",
    "look_at": "dano.vision.camera",
    "project": "dano.vision.camera",
    "save_camera": "dano.vision.camera",
    "Views": "dano.vision.datasets",
    "load_nerf_synthetic": "dano.vision.datasets",
    "FitConfig": "dano.vision.configs",
    "GridModel": "dano.vision.configs",
    "MlpModel": "dano.vision.configs",
    "TrackConfig": "dano.vision.configs",
    "fit_field": "dano.vision.fit",
    "box_downscale": "dano.vision.media",
    "colour_key_masks": "dano.vision.media",
    "load_frames": "dano.vision.media",
    "load_masks": "dano.vision.media",
    "read_image": "dano.vision.media",
    "read_mask": "dano.vision.media",
    "MaskConfig": "dano.vision.observation",
    "identify_mask_files": "dano.vision.pixels",
    "identify_masks": "dano.vision.pixels",
    "bounding_sphere": "dano.vision.synthetic",
    "framing_distance": "dano.vision.synthetic",
    "render_mesh_video": "dano.vision.synthetic",
    "render_views": "dano.vision.synthetic",
    "sphere_cameras": "dano.vision.synthetic",
    "track": "dano.vision.track",
}

if TYPE_CHECKING:
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
    from dano.vision.configs import FitConfig, GridModel, MlpModel, TrackConfig
    from dano.vision.datasets import Views, load_nerf_synthetic
    from dano.vision.fit import fit_field
    from dano.vision.media import box_downscale, colour_key_masks, load_frames, load_masks, read_image, read_mask
    from dano.vision.observation import MaskConfig
    from dano.vision.pixels import identify_mask_files, identify_masks
    from dano.vision.synthetic import bounding_sphere, framing_distance, render_mesh_video, render_views, sphere_cameras
    from dano.vision.track import track


# render_video: renamed in 0.2 (dano.sim.render.render_video renders a simulation); goes in 0.3
__getattr__, __dir__ = attach(__name__, _LAZY, renamed={"render_video": "render_mesh_video"})

__all__ = [
    "Camera", "FitConfig", "GridModel", "MlpModel", "MaskConfig", "TrackConfig", "Views", "VisionDataError",
    "bounding_sphere", "box_downscale", "camera_from_fov", "camera_rays", "colour_key_masks", "fit_field",
    "framing_distance", "identify_mask_files", "identify_masks", "load_camera", "load_frames", "load_masks",
    "load_nerf_synthetic", "look_at", "project", "read_image", "read_mask", "render_mesh_video", "render_views",
    "save_camera", "sphere_cameras", "track",
]  # fmt: skip
