"""The report as a document (``experiments.report.document``): a self-contained HTML page."""

from __future__ import annotations

import base64
import io
import re
import shutil

import imageio.v3 as iio

from experiments.report.write import write_report
from tests.experiments.saved_results import referenced_files


def embedded_images(html: str) -> list[tuple[str, bytes]]:
    """``(mime, bytes)`` of every ``data:`` image of a page; fails on any other reference."""
    refs = re.findall(r'(?:src|href)="([^"]+)"', html)
    assert refs and all(r.startswith("data:image/") for r in refs), [r[:60] for r in refs]
    out = []
    for ref in refs:
        head, data = ref[len("data:") :].split(";base64,", 1)
        out.append((head, base64.b64decode(data, validate=True)))
    return out


def test_html_alone_shows_every_figure(report_path, tmp_path):
    alone = tmp_path / "alone"
    alone.mkdir()
    shutil.copy(report_path.with_suffix(".html"), alone / "report.html")
    html = (alone / "report.html").read_text()
    assert 'src="figures/' not in html and "figures/" not in re.sub(r"data:[^\"]+", "", html)
    images = embedded_images(html)
    md_refs = referenced_files(report_path.read_text(), html=False)
    assert len(images) == len(md_refs) >= 10
    for (mime, raw), ref in zip(images, md_refs, strict=True):
        assert mime == ("image/gif" if ref.endswith(".gif") else "image/png"), ref
        pixels = iio.imread(io.BytesIO(raw), index=None)  # every frame decodes
        assert pixels.shape[-1] in (3, 4) and pixels[..., :3].std() > 10, ref


def test_a_gif_over_the_limit_is_embedded_as_a_labelled_still(results_copy, monkeypatch):
    from experiments.report import document

    monkeypatch.setattr(document, "GIF_EMBED_LIMIT", 1000)
    path = write_report(results_copy)
    html = path.with_suffix(".html").read_text()
    assert "data:image/gif" not in html
    assert "STILL (last frame) of the animation" in html and "figures/episode.gif" in html
    assert all(mime == "image/png" for mime, _ in embedded_images(html))
    assert "](figures/episode.gif)" in path.read_text()  # Markdown still links the GIF
