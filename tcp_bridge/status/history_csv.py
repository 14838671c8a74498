"""The status page's history as CSV: ``GET /api/history.csv`` (:mod:`.http`).

The same samples as ``/api/history`` (:meth:`.sampler.Sampler.history_body`: the last
minute, oldest first), one row per sample, for a spreadsheet, pandas or PlotJuggler:

* ``time [s]``: the sample's start, Unix time (the sampler's clock, ``time.time``),
  in seconds with millisecond digits; the page shows the same instants;
* per axis, ``axis N position [user units]`` and ``axis N velocity [user units/s]``:
  the R12 and R14 replies of that sample, as a client reads them; an empty cell
  where the read failed (the page shows a gap there too).

RFC 4180 (CSV): comma-separated, a header row, CRLF line ends; the numbers are the
replies' own text (no rounding here). Pure: a body in, text out.
"""
from __future__ import annotations

import csv
import io
from typing import Any, Mapping

CONTENT_TYPE = "text/csv; charset=utf-8; header=present"  # RFC 4180 section 3
FILENAME = "tcp-bridge-history.csv"


def _cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, float) and value.is_integer():
        return str(int(value))
    return str(value)


def history_csv(body: Mapping[str, Any]) -> str:
    """``/api/history``'s body (``axes``, ``samples``) as CSV text."""
    axes = list(body.get("axes", []))
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\r\n")
    header = ["time [s]"]
    for addr in axes:
        header += [f"axis {addr} position [user units]", f"axis {addr} velocity [user units/s]"]
    writer.writerow(header)
    for sample in body.get("samples", []):
        row = [f"{float(sample['t']):.3f}"]
        for k in range(len(axes)):
            row += [_cell(sample["position"][k]), _cell(sample["velocity"][k])]
        writer.writerow(row)
    return out.getvalue()


__all__ = ["CONTENT_TYPE", "FILENAME", "history_csv"]
