"""MuJoCo MJX, imported without its chatter on stdout.

MJX prints "Failed to import warp: ..." (twice) with `print` when the optional NVIDIA Warp backend is
absent; on stdout that breaks every command whose output a tool parses (`dano sysid --json`). The
message is diverted while MJX is first imported; stdout is restored at once.
"""

import contextlib
import io

with contextlib.redirect_stdout(io.StringIO()):
    from mujoco import mjx

__all__ = ["mjx"]
