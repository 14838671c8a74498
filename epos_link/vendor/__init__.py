"""Third-party files shipped inside the package, so nothing is fetched at run time.

``uplot/``: uPlot 1.6.32 (MIT, Leon Sorokin; ``uplot/LICENSE``), a small maintained
time-series chart for the browser, taken unchanged from the npm registry's ``uplot``
package (``dist/uPlot.iife.min.js``, ``dist/uPlot.min.css``; tarball sha1
c800a63b432bad692d6d746f44f0882aa73a49ae, integrity
sha512-KIMVnG68zvu5XXUbC4LQEPnhwOxBuLyW1AHtpm6IKTXImkbLgkMy+jabjLgSLMasNuGGzQm/ep3tOkyTxpiQIw==).
It draws the HTML plots of ``epos-link record`` (:mod:`epos_link.tools.plot`) and the
bridge's status page (:mod:`tcp_bridge.status.page`): a cursor with the values at
its time, zoom, legends under the chart, gaps at missing values. Both inline it, so
a plot or the page works with no network at all (no CDN).

To update: ``npm pack uplot@VERSION``, copy the two files and LICENSE, change the
version and hashes above.
"""
from __future__ import annotations

from functools import lru_cache
from pathlib import Path

UPLOT_VERSION = "1.6.32"


@lru_cache(maxsize=None)
def _text(name: str) -> str:
    # A plain path, not importlib.resources: that imports zipfile and with it threading,
    # and the status page that inlines these files is a pure module (tests/test_purity.py).
    return (Path(__file__).parent / "uplot" / name).read_text(encoding="utf-8")


def uplot_js() -> str:
    """uPlot's browser build (an IIFE defining ``uPlot``), its licence banner first."""
    return _text("uPlot.iife.min.js")


def uplot_css() -> str:
    return _text("uPlot.min.css")


def uplot_license() -> str:
    return _text("LICENSE")


def inline_script(source: str) -> str:
    """``source`` made safe inside an HTML ``<script>`` element (no ``</script`` in it)."""
    return source.replace("</", "<\\/")


__all__ = ["UPLOT_VERSION", "inline_script", "uplot_css", "uplot_js", "uplot_license"]
