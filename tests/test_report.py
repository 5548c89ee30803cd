"""The self-contained HTML report, opened in a real browser (headless Chromium)."""

import imageio.v3 as iio
import numpy as np
import pytest

from dano.report import ReportError, Section, write_report
from helpers import browser_screenshot

ORANGE = (255, 128, 0)


def _media(tmp_path):
    square = np.zeros((120, 160, 3), np.uint8)
    square[:] = ORANGE
    iio.imwrite(tmp_path / "square.png", square)
    frames = np.zeros((8, 64, 64, 3), np.uint8)
    frames[:, :, :, 2] = np.linspace(0, 255, 8, dtype=np.uint8)[:, None, None]
    iio.imwrite(tmp_path / "clip.mp4", frames, fps=8, codec="libx264", plugin="pyav")
    return tmp_path / "square.png", tmp_path / "clip.mp4"


def test_a_report_is_one_file_that_a_browser_shows_with_no_console_message(tmp_path):
    picture, clip = _media(tmp_path)
    table = [("quantity", "value"), ("mass [kg]", 0.5), ("<b>escaped</b>", "a & b")]
    sections = [Section("Mass properties", "What was measured.", table, [picture, clip], "dano demo -o out")]
    page = write_report(tmp_path / "report.html", "A report", sections, note="a note")
    text = page.read_text()
    assert "&lt;b&gt;escaped&lt;/b&gt;" in text and "a &amp; b" in text and "dano demo -o out" in text
    # Self-contained: every picture and video is inside the page, nothing is fetched.
    assert text.count('src="data:image/png;base64,') == 1 and text.count('src="data:video/mp4;base64,') == 1
    assert "http" not in text and "file:" not in text
    (tmp_path / "square.png").unlink()  # the page no longer needs its media
    (tmp_path / "clip.mp4").unlink()
    shot, console = browser_screenshot(page, tmp_path / "shot.png")
    assert console == []
    orange = np.all(np.abs(shot[..., :3].astype(int) - ORANGE) < 30, axis=-1)
    assert orange.sum() > 0.8 * 120 * 160  # the embedded picture is shown


def test_bad_reports_are_named_errors_and_write_nothing(tmp_path):
    picture, _ = _media(tmp_path)
    with pytest.raises(ReportError, match="must end in .html"):
        write_report(tmp_path / "report.htm", "r", [Section("s", media=[picture])])
    with pytest.raises(ReportError, match="no such file to embed"):
        write_report(tmp_path / "report.html", "r", [Section("s", media=[tmp_path / "gone.png"])])
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(ReportError, match="cannot embed a .txt file"):
        write_report(tmp_path / "report.html", "r", [Section("s", media=[tmp_path / "notes.txt"])])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["clip.mp4", "notes.txt", "square.png"]


def test_a_commands_picture_is_its_own_png_or_one_drawn_for_the_page_and_removed(tmp_path):
    from dano.cli.reports import picture

    picture_png, _ = _media(tmp_path)
    drawn = []
    with picture(str(picture_png), drawn.append) as png:
        assert png == picture_png and drawn == []  # the command wrote a PNG: that one
    with picture(str(tmp_path / "fit.pdf"), lambda p: iio.imwrite(p, np.zeros((4, 4, 3), np.uint8))) as png:
        assert png.suffix == ".png" and png.is_file() and png.parent != tmp_path  # a PDF cannot be embedded
    assert not png.exists()
