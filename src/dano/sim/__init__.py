"""DANOs inside MuJoCo MJX: scenes, the contact step, rollouts."""

from dano.sim.scene import DanoBody, Params, Primitive, Scene, World, compile_scene, pairs
from dano.sim.step import Trajectory, contact_xfrc, rollout, scaled_model, step

__all__ = [
    "DanoBody", "Params", "Primitive", "Scene", "Trajectory", "World", "compile_scene", "contact_xfrc", "pairs",
    "rollout", "scaled_model", "step",
]  # fmt: skip
