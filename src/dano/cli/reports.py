"""`--report OUT.html` on the commands that solve or measure something: one self-contained page
(`dano.report`) with the command's results, its pictures and the command line that reproduces it."""

import argparse
import contextlib
import shlex
import tempfile
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from dano.cli.arguments import _output

if TYPE_CHECKING:  # `dano --help` imports this module: it loads nothing heavy (dano.report's I/O loads JAX)
    from dano.report import Section


def add_report(parser: argparse.ArgumentParser, what: str) -> None:
    parser.add_argument("--report", type=_output(".html"), metavar="OUT.html",
                        help=f"also write one self-contained HTML page: {what}, and this command line")  # fmt: skip


@contextlib.contextmanager
def picture(written: str | None, draw: Callable[[Path], object]) -> Iterator[Path]:
    """The command's PNG if it wrote one, else one drawn by `draw` into a folder removed afterwards."""
    if written is not None and written.lower().endswith(".png"):
        yield Path(written)
        return
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "picture.png"
        draw(path)
        yield path


def write_command_report(args: argparse.Namespace, title: str, sections: "Sequence[Section]") -> Path:
    from dano.report import Section, write_report

    command = shlex.join(["dano", *args.argv])
    return write_report(args.report, title, [*sections, Section("Reproduce", "Written by:", command=command)])
