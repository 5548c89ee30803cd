"""DANOs inside MuJoCo MJX: scenes, the contact step, rollouts."""

from dano.sim.scene import (
    DanoBody,
    Params,
    Primitive,
    Robot,
    Scene,
    SceneError,
    World,
    compile_scene,
    load_scene,
    pairs,
    panda,
)
from dano.sim.step import Trajectory, contact_xfrc, rollout, scaled_model, step

__all__ = [
    "DanoBody", "Params", "Primitive", "Robot", "Scene", "SceneError", "Trajectory", "World", "compile_scene",
    "contact_xfrc", "load_scene", "pairs", "panda", "rollout", "scaled_model", "step",
]  # fmt: skip
