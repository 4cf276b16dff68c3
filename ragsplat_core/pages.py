"""Self-contained HTML pages of a run (a survey's `report.html`, an ablation's): Jinja2 templates in
`templates/`, every figure inlined as PNG data, so a page opens offline, mailed or copied alone."""

from __future__ import annotations

import base64
import io
import re
from pathlib import Path

from ragsplat.outputs import atomic_path

TEMPLATES = Path(__file__).with_name("templates")
FIGURE_DPI = 90
# the check a browser test reads: how many of the page's images decoded, set on the body once it has loaded
IMAGES_LOADED = "images"


def pyplot():
    """matplotlib's pyplot drawing to files only (no display): every figure the project draws goes through
    it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def figure_uri(fig) -> str:
    """A matplotlib figure as a PNG data URI (the figure closed after)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=FIGURE_DPI)
    pyplot().close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode()


def file_uri(path: Path) -> str | None:
    """A PNG file as a data URI, None where there is none."""
    path = Path(path)
    return "data:image/png;base64," + base64.b64encode(path.read_bytes()).decode() if path.is_file() else None


def markdown_blocks(text: str) -> list[dict]:
    """Markdown as the ablation's tables write it -> blocks: {"heading": str}, {"table": {"head": [...],
    "rows": [[...], ...]}} (pipe tables, the separator row dropped) or {"text": str} (a paragraph)."""
    blocks, para, table = [], [], None

    def cells(line: str) -> list[str]:
        return [c.strip() for c in line.strip().strip("|").split("|")]

    def flush():
        nonlocal table
        if para:
            blocks.append({"text": " ".join(para)})
            para.clear()
        if table is not None:
            blocks.append({"table": table})
            table = None

    for line in text.splitlines():
        if line.startswith("|"):
            if para:
                flush()
            if table is None:
                table = {"head": cells(line), "rows": []}
            elif not re.fullmatch(r"\|?[\s:|-]+\|?", line.strip()):
                table["rows"].append(cells(line))
        elif line.startswith("#"):
            flush()
            blocks.append({"heading": line.lstrip("#").strip()})
        elif line.strip():
            if table is not None:
                flush()
            para.append(line.strip())
        else:
            flush()
    flush()
    return blocks


def write_page(path: Path, template: str, **context) -> Path:
    """`templates/template` rendered with `context` (autoescaped; a missing name is an error) into `path`,
    atomically. Returns the path."""
    import jinja2

    env = jinja2.Environment(loader=jinja2.FileSystemLoader(TEMPLATES), autoescape=True,
                             undefined=jinja2.StrictUndefined)
    page = env.get_template(template).render(images_loaded=IMAGES_LOADED, **context)
    with atomic_path(path) as tmp:
        Path(tmp).write_text(page)
    return Path(path)
