"""Process settings dano needs, applied when dano is imported: before JAX starts its CPU backend
and before MuJoCo is imported.

MuJoCo renders headless through EGL (`MUJOCO_GL=egl` unless set): it reads the variable on import.

XLA's CPU fusion emitters (jaxlib 0.10) duplicate work inside fusions along a kinematic chain: the
cost grows exponentially with the chain's depth once the bodies' frames are rotated. MJX's forward
kinematics of the Franka Panda took 50 ms per call with them and 0.2 ms without; a 9-link chain with
rotated frames 4.9 s and 0.17 ms (`bench/xla_fusion.py` measures both). The legacy emitters have no
such blow-up, so dano selects them unless `XLA_FLAGS` already says otherwise.
"""

import os
import sys
import warnings

FLAG = "--xla_cpu_use_fusion_emitters=false"


def configure() -> None:
    """Both settings: MuJoCo's headless renderer, and XLA's CPU emitters (`configure_xla`)."""
    os.environ.setdefault("MUJOCO_GL", "egl")
    configure_xla()


def configure_xla() -> None:
    """Adds `FLAG` to `XLA_FLAGS` unless the user set that option; warns if JAX already started."""
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_cpu_use_fusion_emitters" in flags:
        return
    os.environ["XLA_FLAGS"] = f"{flags} {FLAG}".strip()
    if "jax" in sys.modules and _backends_started():
        warnings.warn(
            f"JAX started before dano was imported, so XLA_FLAGS={FLAG} does not apply: robot arms in MJX may "
            "simulate 100x slower on CPU. Import dano first, or set the flag in the environment.",
            RuntimeWarning,
            stacklevel=3,
        )


def _backends_started() -> bool:
    try:
        from jax._src import xla_bridge

        return bool(xla_bridge.backends_are_initialized())
    except (ImportError, AttributeError):
        return False


configure()
