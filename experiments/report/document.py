"""A small document model (headings, paragraphs, lists, tables, images) rendered to Markdown
and to a self-contained HTML page (images embedded as ``data:`` URIs).
"""

from __future__ import annotations

import html
import re
from collections.abc import Sequence
from pathlib import Path


class Document:
    """A small document model rendered to both Markdown and HTML, so they match."""

    def __init__(self) -> None:
        self.blocks: list[tuple] = []

    def heading(self, text: str, level: int = 2) -> None:
        self.blocks.append(("heading", level, text))

    def paragraph(self, text: str) -> None:
        self.blocks.append(("paragraph", text))

    def bullets(self, items: Sequence[str]) -> None:
        self.blocks.append(("bullets", list(items)))

    def table(self, header: Sequence[str], rows: Sequence[Sequence[str]]) -> None:
        self.blocks.append(("table", list(header), [list(r) for r in rows]))

    def image(self, relpath: str, caption: str) -> None:
        self.blocks.append(("image", relpath, caption))

    # ---- Markdown

    def markdown(self) -> str:
        out = []
        for block in self.blocks:
            kind = block[0]
            if kind == "heading":
                out.append("#" * block[1] + " " + block[2])
            elif kind == "paragraph":
                out.append(block[1])
            elif kind == "bullets":
                out.append("\n".join(f"- {item}" for item in block[1]))
            elif kind == "table":
                header, rows = block[1], block[2]
                lines = ["| " + " | ".join(_md_cell(h) for h in header) + " |"]
                lines.append("|" + "|".join("---" for _ in header) + "|")
                lines += ["| " + " | ".join(_md_cell(c) for c in row) + " |" for row in rows]
                out.append("\n".join(lines))
            elif kind == "image":
                out.append(f"![{block[2]}]({block[1]})\n\n*{block[2]}*")
        return "\n\n".join(out) + "\n"

    # ---- HTML

    def html(self, title: str, base_dir: str | Path | None = None) -> str:
        """The document as one HTML page titled ``title``; images embedded from ``base_dir``
        (:func:`embedded_image`), or linked when ``None``.
        """
        body = []
        for block in self.blocks:
            kind = block[0]
            if kind == "heading":
                body.append(f"<h{block[1]}>{_inline_html(block[2])}</h{block[1]}>")
            elif kind == "paragraph":
                body.append(f"<p>{_inline_html(block[1])}</p>")
            elif kind == "bullets":
                items = "".join(f"<li>{_inline_html(i)}</li>" for i in block[1])
                body.append(f"<ul>{items}</ul>")
            elif kind == "table":
                head = "".join(f"<th>{_inline_html(h)}</th>" for h in block[1])
                rows = "".join(
                    "<tr>" + "".join(f"<td>{_inline_html(c)}</td>" for c in row) + "</tr>"
                    for row in block[2]
                )
                body.append(f"<table><thead><tr>{head}</tr></thead><tbody>{rows}</tbody></table>")
            elif kind == "image":
                src, caption = block[1], block[2]
                if base_dir is not None:
                    src, caption = embedded_image(Path(base_dir) / block[1], caption)
                src, cap = html.escape(src, quote=True), _inline_html(caption)
                body.append(
                    f'<figure><img src="{src}" alt="{html.escape(block[2], quote=True)}">'
                    f"<figcaption>{cap}</figcaption></figure>"
                )
        return _HTML_TEMPLATE.format(title=html.escape(title), body="\n".join(body))


#: Largest GIF embedded whole in report.html [bytes]; a larger one is shown as a still.
GIF_EMBED_LIMIT = 6 * 1024**2

_MIME = {".png": "image/png", ".gif": "image/gif", ".jpg": "image/jpeg", ".svg": "image/svg+xml"}


def embedded_image(path: str | Path, caption: str) -> tuple[str, str]:
    """A ``data:`` URI of an image file and its caption (a GIF over :data:`GIF_EMBED_LIMIT`:
    a PNG of its last frame, said in the caption).

    Raises:
        FileNotFoundError: naming the image, if it does not exist.
    """
    import base64

    path = Path(path)
    data = path.read_bytes()
    mime = _MIME.get(path.suffix.lower(), "application/octet-stream")
    if mime == "image/gif" and len(data) > GIF_EMBED_LIMIT:
        import io

        from PIL import Image

        with Image.open(path) as gif_image:
            gif_image.seek(gif_image.n_frames - 1)
            buf = io.BytesIO()
            gif_image.convert("RGB").save(buf, format="PNG")
        data, mime = buf.getvalue(), "image/png"
        caption = (
            f"STILL (last frame) of the animation: the GIF ({len(path.read_bytes()) / 1024**2:.1f}"
            f" MB) is over the {GIF_EMBED_LIMIT / 1024**2:g} MB embedding limit and is at "
            f"figures/{path.name} beside the report. {caption}"
        )
    return f"data:{mime};base64,{base64.b64encode(data).decode('ascii')}", caption


_HTML_TEMPLATE = """<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<title>{title}</title>
<style>
body {{ font-family: system-ui, sans-serif; max-width: 1150px; margin: 2em auto;
       padding: 0 1em; color: #222; line-height: 1.45; }}
table {{ border-collapse: collapse; margin: 1em 0; font-size: 0.9em; }}
th, td {{ border: 1px solid #ccc; padding: 0.3em 0.6em; text-align: left;
         vertical-align: top; }}
th {{ background: #f2f2f2; }}
tbody tr:nth-child(even) {{ background: #fafafa; }}
code {{ background: #f4f4f4; padding: 0 0.2em; }}
figure {{ margin: 1.2em 0; }}
img {{ max-width: 100%; border: 1px solid #ddd; }}
figcaption {{ font-style: italic; font-size: 0.9em; color: #555; }}
</style>
</head>
<body>
{body}
</body>
</html>
"""


def _md_cell(text: str) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def _inline_html(text: str) -> str:
    """Escape text and turn Markdown's ``code`` and **bold** spans into HTML."""
    escaped = html.escape(str(text))
    escaped = re.sub(r"`([^`]+)`", r"<code>\1</code>", escaped)
    return re.sub(r"\*\*([^*]+)\*\*", r"<strong>\1</strong>", escaped)
