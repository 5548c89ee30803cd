"""One self-contained HTML page of results: text, tables, pictures and videos, with the commands that
reproduce them.

Pictures (PNG) and videos (MP4, GIF) are embedded as data URIs, so the page opens from disk in any
browser with no server and no other file, and can be mailed or attached as it is. The page has no
script. `dano demo` writes one (`report.html`).
"""

import base64
import dataclasses
import html
from collections.abc import Sequence
from pathlib import Path

from dano.errors import DanoError
from dano.io import atomic_write

_MEDIA = {".png": "image/png", ".gif": "image/gif", ".mp4": "video/mp4"}
_STYLE = """
body { font-family: system-ui, sans-serif; max-width: 62rem; margin: 2rem auto; padding: 0 1rem; color: #222; }
h1 { font-size: 1.6rem; } h2 { font-size: 1.25rem; margin-top: 2.2rem; border-bottom: 1px solid #ddd; }
table { border-collapse: collapse; margin: 0.8rem 0; font-variant-numeric: tabular-nums; }
th, td { border: 1px solid #ccc; padding: 0.25rem 0.6rem; text-align: left; }
th { background: #f3f3f3; }
img, video { max-width: 100%; margin: 0.5rem 0; border: 1px solid #eee; }
pre { background: #f6f6f6; padding: 0.6rem; overflow-x: auto; }
.note { color: #666; font-size: 0.9rem; }
"""


class ReportError(DanoError):
    """A report that cannot be written as asked (a missing or unknown media file, a bad path)."""


@dataclasses.dataclass(frozen=True)
class Section:
    """One part of a report.

    Attributes:
        title: its heading.
        text: a paragraph (plain text; escaped).
        table: rows of cells, the first row the header (cells are shown with `str`).
        media: PNG, GIF or MP4 files, embedded in this order.
        command: the command (or code) that reproduces the section, shown as is.
    """

    title: str
    text: str = ""
    table: Sequence[Sequence[object]] = ()
    media: Sequence[str | Path] = ()
    command: str = ""


def write_report(path: str | Path, title: str, sections: Sequence[Section], note: str = "") -> Path:
    """Writes the page (module docstring) to `path` (.html), atomically, and returns the path.

    Raises:
        ReportError: the path does not end in .html, or a media file is missing or of another kind;
            nothing is written then.
    """
    path = Path(path)
    if path.suffix.lower() != ".html":
        raise ReportError(f"the report must end in .html, got {path.name!r}")
    parts = [f"<h1>{html.escape(title)}</h1>"]
    if note:
        parts.append(f'<p class="note">{html.escape(note)}</p>')
    parts += [_section(s) for s in sections]
    page = (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        f"<title>{html.escape(title)}</title><style>{_STYLE}</style></head>\n<body>\n"
        + "\n".join(parts)
        + "\n</body></html>\n"
    )
    with atomic_write(path) as tmp:
        tmp.write_text(page, encoding="utf-8")
    return path


def _section(s: Section) -> str:
    out = [f"<h2>{html.escape(s.title)}</h2>"]
    if s.text:
        out.append(f"<p>{html.escape(s.text)}</p>")
    if s.table:
        head, *rows = s.table
        out.append("<table><tr>" + "".join(f"<th>{html.escape(str(c))}</th>" for c in head) + "</tr>")
        out += ["<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in row) + "</tr>" for row in rows]
        out.append("</table>")
    out += [_embed(Path(m)) for m in s.media]
    if s.command:
        out.append(f"<pre>{html.escape(s.command)}</pre>")
    return "\n".join(out)


def _embed(path: Path) -> str:
    kind = _MEDIA.get(path.suffix.lower())
    if kind is None:
        raise ReportError(f"{path}: cannot embed a {path.suffix or 'suffix-less'} file (PNG, GIF or MP4)")
    if not path.is_file():
        raise ReportError(f"{path}: no such file to embed")
    uri = f"data:{kind};base64,{base64.b64encode(path.read_bytes()).decode('ascii')}"
    name = html.escape(path.name)
    if kind == "video/mp4":
        return f'<video controls loop muted playsinline title="{name}" src="{uri}"></video>'
    return f'<img alt="{name}" title="{name}" src="{uri}">'
