"""The HTML pieces of ``spacepose report``'s page: a table, a figure embedded as a PNG data URI,
and file names as text any writer and font takes.

The sections of :mod:`spacepose.tools.report_runs` and :mod:`spacepose.tools.report` build their
parts of the page from these.
"""

from __future__ import annotations

import html
from collections.abc import Iterable, Sequence

from spacepose.tools import plots


def shown(name: str) -> str:
    """A file name as text any writer and font takes: bytes that are not UTF-8 (Python holds
    them as surrogates) become backslash escapes.

    Parameters
    ----------
    name
        A file or folder name, possibly holding surrogates.

    Returns
    -------
    The name, valid UTF-8.
    """
    return name.encode("utf-8", "backslashreplace").decode("utf-8")


def html_table(header: Sequence[str], rows: Iterable[Sequence[object]]) -> str:
    """An HTML table, every cell escaped.

    Parameters
    ----------
    header
        The column titles.
    rows
        The rows, one value a column; floats are written with 4 significant digits.

    Returns
    -------
    The ``<table>`` element.
    """

    def cell(v: object) -> str:
        if isinstance(v, float):
            return f"{v:.4g}"
        return html.escape(str(v))

    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{cell(v)}</td>" for v in r) + "</tr>" for r in rows)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def html_figure(fig_png: bytes, caption: str) -> str:
    """A figure embedded in the page as a PNG data URI, with its caption.

    Parameters
    ----------
    fig_png
        The PNG bytes.
    caption
        The caption, also the image's ``alt`` text.

    Returns
    -------
    The ``<figure>`` element.
    """
    uri = plots.png_data_uri(fig_png)
    return (
        f'<figure><img src="{uri}" alt="{html.escape(caption)}"><figcaption class="muted">'
        f"{html.escape(caption)}</figcaption></figure>"
    )
