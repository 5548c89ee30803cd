"""The `dano` command: thin subcommands that parse, call the library and print.

`arguments` holds the checked argument types; `objects` (build, info, simulate, demo), `solvers`
(sysid, trajopt) and `media` (render-views, fit-field, track, compare) each add their subcommands'
options and run them.
"""

import argparse
import os
import re
import sys
import warnings
from pathlib import Path

from dano.cli.arguments import UsageError, _Parser
from dano.cli.media import _add_compare, _add_fit_field, _add_render_views, _add_track
from dano.cli.objects import _add_build, _add_demo, _add_export, _add_info, _add_simulate, _add_view, info_dict
from dano.cli.solvers import _add_sysid, _add_trajopt
from dano.errors import DanoError

__all__ = ["CACHE_VARIABLE", "RENAMED", "UsageError", "compilation_cache", "info_dict", "main", "parser"]


def parser() -> argparse.ArgumentParser:
    """The whole command line: one subparser per command, each added by its module."""
    from dano import __version__

    p = _Parser(prog="dano", description="Dynamics-Augmented Neural Objects")
    p.add_argument("--version", action="version", version=f"dano {__version__}")
    sub = p.add_subparsers(dest="command", required=True)
    for add in (_add_build, _add_info, _add_simulate, _add_export, _add_view, _add_sysid, _add_trajopt, _add_compare,
                _add_render_views, _add_fit_field, _add_track, _add_demo):  # fmt: skip
        add(sub)
    return p


RENAMED = {
    ("demo", "--out"): "-o/--output",
    ("sysid", "--scene"): "the positional SCENE (dano sysid SCENE.toml ...)",
    ("sysid", "--max-steps"): "--max-iterations",
    ("sysid", "--window"): "--window-frames",
    ("render-views", "--resolution"): "--image-size",
    ("track", "--iterations"): "--steps",
}
"""Old spellings still accepted for one release (they go in 0.3), each with a note on stderr: one
word per concept across commands (`-o` for output, `--max-iterations` for a solver's cap, `--steps`
for a fixed count, `--resolution` for grid nodes, `--window` for a density window)."""


def _renamed_notes(command: str, argv: list[str]) -> None:
    for token in argv:
        new = RENAMED.get((command, token.split("=", 1)[0]))
        if new is not None:
            print(f"dano {command}: note: {token.split('=', 1)[0]} is now {new} (the old name goes in 0.3)",
                  file=sys.stderr)  # fmt: skip


CACHE_VARIABLE = "DANO_COMPILATION_CACHE"
"""Environment variable: the folder of the command line's persistent compilation cache (default
`~/.cache/dano/jax`), or `off`."""


def compilation_cache() -> str | None:
    """Turns on JAX's persistent compilation cache for this command (not on import: a library
    changes no process setting) and returns its folder, or None when `DANO_COMPILATION_CACHE=off`.
    A second run of the same command with the same shapes then loads its XLA programs from disk
    instead of compiling them (a simulation's rollout, an identification's Jacobians)."""
    import jax

    path = os.environ.get(CACHE_VARIABLE) or str(Path.home() / ".cache" / "dano" / "jax")
    if path.lower() in ("off", "0", "none"):
        return None
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
    return path


def attach_negative_values(argv: list[str]) -> list[str]:
    """`--gravity -0.27,-0.27,-0.92` as `--gravity=-0.27,...`: argparse takes a token that starts with
    '-' and is not a plain number for an option, so comma-separated negative values need the '='."""
    out: list[str] = []
    for token in argv:
        if out and out[-1].startswith("--") and "=" not in out[-1] and re.match(r"-[\d.]", token) and "," in token:
            out[-1] = f"{out[-1]}={token}"
        else:
            out.append(token)
    return out


def _warning_line(command: str):
    """Warnings as one line on stderr, like errors: `dano sysid: UnitsWarning: ...`."""

    def show(message, category, filename, lineno, file=None, line=None):
        print(f"dano {command}: {category.__name__}: {message}", file=sys.stderr if file is None else file)

    return show


def main(argv: list[str] | None = None) -> int:
    argv = attach_negative_values(sys.argv[1:] if argv is None else list(argv))
    try:
        args = parser().parse_args(argv)
    except SystemExit as e:  # --help, --version (0) or a usage error (2, its one line already printed)
        return e.code if isinstance(e.code, int) else 2
    _renamed_notes(args.command, argv)
    args.argv = argv  # the command line, for the reports that show how to reproduce them
    import jax  # after parsing: `dano --help` and usage errors need no JAX

    # Float64 throughout, as the tests run: identification needs it (in float32 the Gauss-Newton
    # Hessian of a stiff contact overflows), and one precision keeps every command's numbers alike.
    jax.config.update("jax_enable_x64", True)
    compilation_cache()
    try:
        with warnings.catch_warnings():  # restored on the way out: the caller's process is left as it was
            warnings.showwarning = _warning_line(args.command)
            args.run(args)
    except DanoError as e:
        print(f"dano {args.command}: {type(e).__name__}: {e}", file=sys.stderr)
        return 2
    except OSError as e:  # the disk: full, read-only, permissions (outputs are written atomically)
        print(f"dano {args.command}: {type(e).__name__}: {e}", file=sys.stderr)
        return 1
    return 0
