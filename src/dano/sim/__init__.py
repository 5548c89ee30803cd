"""DANOs inside MuJoCo MJX: scenes, the contact step, rollouts.

Modules, bottom up: `scene` (declarations), `world` (the compiled scene the step reads), `robots`
(URDF/MJCF robots), `compile` (a `Scene` to MuJoCo and a `World`), `toml` (scene files), `step`
and `implicit` (the contact step), `run` (rollouts, `Simulation`), `render`.
"""

import warnings

from dano.sim.compile import Compiled, compile_scene
from dano.sim.scene import DanoBody, Primitive, Robot, Scene, SceneError
from dano.sim.step import Trajectory, contact_xfrc, rollout, scaled_model, step
from dano.sim.toml import load_scene
from dano.sim.world import Params, World, pair_name, pairs


def __getattr__(name: str):
    if name == "panda":  # moved to dano.assets in 0.2; this alias goes in 0.3
        warnings.warn("dano.sim.panda moved to dano.assets.panda", DeprecationWarning, stacklevel=2)
        from dano.assets import panda

        return panda
    raise AttributeError(f"module 'dano.sim' has no attribute {name!r}")


__all__ = [
    "Compiled", "DanoBody", "Params", "Primitive", "Robot", "Scene", "SceneError", "Trajectory", "World",
    "compile_scene", "contact_xfrc", "load_scene", "pair_name", "pairs", "rollout", "scaled_model", "step",
]  # fmt: skip
