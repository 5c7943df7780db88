"""The report as one PDF (`calib report ... --pdf`): the same sections, text,
tables and figures as report.md / report.html, laid out on A4 pages by
matplotlib's PdfPages (no further dependency). Text pages are drawn with
``fig.text`` in a monospace font for tables; every text goes through
``mpl_text`` (a ``$`` from a file is not mathtext, docs/security.md).
"""

from __future__ import annotations

import textwrap
from pathlib import Path

from matplotlib.backends.backend_pdf import PdfPages
from matplotlib.figure import Figure

from calib_cli.io.escape import mpl_text

A4 = (8.27, 11.69)  # inches, portrait
MARGIN = 0.07  # of the page, each side
LINE = 0.0165  # of the page height per line of body text
WRAP = 98  # characters per line of body text
MONO_WRAP = 110


class _Pages:
    """Lines of text flowing over A4 pages; figures on pages of their own."""

    def __init__(self, pdf: PdfPages, title: str):
        self.pdf, self.title, self.page, self.y, self.n = pdf, title, None, 0.0, 0

    def _new(self) -> None:
        self.flush()
        self.page = Figure(figsize=A4)
        self.n += 1
        self.page.text(1 - MARGIN, MARGIN / 2, f"{mpl_text(self.title)} - page {self.n}",
                       ha="right", va="bottom", fontsize=7, color="0.4")
        self.y = 1 - MARGIN

    def flush(self) -> None:
        if self.page is not None:
            self.pdf.savefig(self.page)
            self.page = None

    def line(self, text: str, size: float = 9, weight: str = "normal", mono: bool = False,
             gap: float = 1.0, color: str = "black") -> None:
        h = LINE * gap * size / 9
        if self.page is None or self.y - h < MARGIN:
            self._new()
        self.y -= h
        self.page.text(MARGIN, self.y, mpl_text(text), fontsize=size, weight=weight,
                       family="monospace" if mono else "sans-serif", va="bottom", color=color)

    def para(self, text: str, **kw) -> None:
        for ln in textwrap.wrap(text, WRAP) or [""]:
            self.line(ln, **kw)
        self.skip(0.4)

    def skip(self, lines: float = 1.0) -> None:
        if self.page is not None:
            self.y -= LINE * lines

    def table(self, t) -> None:
        cols = [list(map(str, t.header))] + [[str(c) for c in r] for r in t.rows]
        n = max(len(r) for r in cols)
        cols = [r + [""] * (n - len(r)) for r in cols]
        width = [max(len(r[j]) for r in cols) for j in range(n)]
        # too wide for the page: the widest columns are cut with an ellipsis
        while sum(width) + 2 * (n - 1) > MONO_WRAP and max(width) > 12:
            j = width.index(max(width))
            width[j] -= 1

        def cell(s, w):
            return s if len(s) <= w else s[: max(w - 1, 0)] + "~"

        if t.caption:
            self.para(t.caption, size=8.5, weight="bold")
        for i, r in enumerate(cols):
            self.line("  ".join(cell(c, w).ljust(w) for c, w in zip(r, width)), size=7,
                      mono=True, weight="bold" if i == 0 else "normal", gap=0.95)
        self.skip(0.8)

    def figure(self, fi, k: int) -> None:
        """The figure on a page of its own, scaled to the page width, caption below."""
        self.flush()
        fw, fh = fi.fig.get_size_inches()
        page = Figure(figsize=A4)
        w = 1 - 2 * MARGIN
        h = min(w * fh / fw * A4[0] / A4[1], 0.7)
        w = h * fw / fh * A4[1] / A4[0]
        import io

        buf = io.BytesIO()
        fi.fig.savefig(buf, format="png", dpi=200)
        buf.seek(0)
        import matplotlib.image as mpimg

        ax = page.add_axes([(1 - w) / 2, 1 - MARGIN - h, w, h])
        ax.imshow(mpimg.imread(buf, format="png"))
        ax.set_axis_off()
        self.page, self.y = page, 1 - MARGIN - h - 0.01
        self.n += 1
        page.text(1 - MARGIN, MARGIN / 2, f"{mpl_text(self.title)} - page {self.n}",
                  ha="right", va="bottom", fontsize=7, color="0.4")
        self.para(f"Figure {k}. {fi.caption}", size=8.5)
        self.flush()


def write_pdf(sections, title: str, path) -> int:
    """Write the report as a PDF at ``path``; returns the number of pages."""
    path = Path(path)
    with PdfPages(path, metadata={"Title": title, "Creator": "calib report"}) as pdf:
        pages = _Pages(pdf, title)
        pages.para(title, size=14, weight="bold")
        k = 0
        for sec in sections:
            pages.skip(0.6)
            pages.para(sec.title, size=12, weight="bold")
            for p in sec.text:
                verdict = p.startswith("Verdict: ")
                color = "black"
                if verdict:
                    word = p.split()[1] if len(p.split()) > 1 else ""
                    color = {"PASS": "#009E73", "FAIL": "#D55E00"}.get(word, "black")
                pages.para(p, weight="bold" if verdict else "normal", color=color)
            for fi in sec.figures:  # the order of report.md and report.html
                k += 1
                pages.figure(fi, k)
            for t in sec.tables:
                pages.table(t)
        pages.flush()
        n = pages.n
    return n
