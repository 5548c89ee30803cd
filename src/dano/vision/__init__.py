"""From pixels: cameras, multi-view datasets, rendered ground truth, videos and masks (`data`)."""

from dano.vision.data import (
    Camera,
    Views,
    VisionDataError,
    bounding_sphere,
    box_downscale,
    camera_from_fov,
    camera_rays,
    colour_key_masks,
    framing_distance,
    load_camera,
    load_frames,
    load_masks,
    load_nerf_synthetic,
    look_at,
    project,
    read_image,
    read_mask,
    render_video,
    render_views,
    save_camera,
    sphere_cameras,
)

__all__ = [
    "Camera", "Views", "VisionDataError", "bounding_sphere", "box_downscale", "camera_from_fov", "camera_rays",
    "colour_key_masks", "framing_distance", "load_camera", "load_frames", "load_masks", "load_nerf_synthetic",
    "look_at", "project", "read_image", "read_mask", "render_video", "render_views", "save_camera", "sphere_cameras",
]  # fmt: skip
