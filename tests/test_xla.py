"""dano's XLA settings (`dano._env`): set on import, never over a user's own choice."""

import os
import subprocess
import sys

from dano._env import FLAG

SHOW = "import os, dano; print(os.environ['XLA_FLAGS'])"


def _flags_after_import(xla_flags: str | None) -> str:
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    if xla_flags is not None:
        env["XLA_FLAGS"] = xla_flags
    return subprocess.run([sys.executable, "-c", SHOW], env=env, capture_output=True, text=True, check=True).stdout


def test_import_turns_the_fusion_emitters_off_and_keeps_other_flags():
    assert _flags_after_import(None).split() == [FLAG]
    assert _flags_after_import("--xla_force_host_platform_device_count=2").split() == [
        "--xla_force_host_platform_device_count=2",
        FLAG,
    ]


def test_a_users_own_choice_is_kept():
    assert _flags_after_import("--xla_cpu_use_fusion_emitters=true").split() == ["--xla_cpu_use_fusion_emitters=true"]
