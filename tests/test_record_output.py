"""``epos-link record``'s outputs, as a user meets them: a path that cannot be written is
one line and exit 2 before anything is sent; a write that fails at the end is one line
and exit 2, and the other outputs are written and named; no output at all is refused.

"Nothing was sent" is seen from ``--trace``: the trace file is created when the link
opens, so a command refused before that leaves none.
"""
from __future__ import annotations

import csv
import os
from pathlib import Path
from typing import Any

import pytest

from epos_link.cli import main
from tests.test_record_plot import plot_panels

URL = "sim://?drives=2"


def record(tmp_path: Path, capsys: pytest.CaptureFixture[str], *outputs: str,
           duration: str = "0.05") -> tuple[int, str, str]:
    code = main(["record", URL, "--node", "2", "statusword", "0x6064", "--duration", duration,
                 "--trace", str(tmp_path / "trace.txt"), *outputs])
    out, err = capsys.readouterr()
    return code, out, err


def refused(tmp_path: Path, capsys: pytest.CaptureFixture[str], *outputs: str) -> str:
    """The one stderr line of a record refused before it sent anything."""
    # Were it not refused, it would record for 5 s and leave a trace.
    code, out, err = record(tmp_path, capsys, *outputs, duration="5")
    assert (code, out) == (2, ""), err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert not (tmp_path / "trace.txt").exists()  # the link was never opened
    return err.rstrip("\n")


@pytest.mark.parametrize("where, reason", [
    ("/nonexistent/x.csv", "No such file or directory"),
    ("{tmp}", "Is a directory"),
    ("{tmp}/ok.csv/x.csv", "Not a directory"),
])
def test_a_csv_that_cannot_be_written_is_refused_before_recording(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], where: str, reason: str) -> None:
    (tmp_path / "ok.csv").write_text("")
    path = where.format(tmp=tmp_path)
    line = refused(tmp_path, capsys, "--csv", path)
    assert line == f"epos-link record: cannot write {path}: {reason}"


@pytest.mark.parametrize("name", ["x.html", "x.png", "x.svg"])
def test_a_plot_that_cannot_be_written_is_refused_before_recording(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], name: str) -> None:
    if not name.endswith(".html"):
        pytest.importorskip("matplotlib", reason="PNG and SVG need matplotlib")
    path = f"/nonexistent/{name}"
    line = refused(tmp_path, capsys, "--csv", str(tmp_path / "ok.csv"), "--plot", path)
    assert line == f"epos-link record: cannot write {path}: No such file or directory"
    assert not (tmp_path / "ok.csv").exists()  # nothing is created by the checks


@pytest.mark.skipif(os.name != "posix" or os.geteuid() == 0, reason="root writes anything")
def test_a_read_only_file_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "locked.csv"
    path.write_text("kept\n")
    path.chmod(0o444)
    line = refused(tmp_path, capsys, "--csv", str(path))
    assert line == f"epos-link record: cannot write {path}: Permission denied"
    assert path.read_text() == "kept\n"


def test_without_csv_or_plot_nothing_is_recorded(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    line = refused(tmp_path, capsys)
    assert line.startswith("epos-link record: nothing would keep the samples: give --csv FILE")


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full (Linux)")
def test_a_full_disk_at_the_end_keeps_the_other_outputs(tmp_path: Path,
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    """/dev/full passes every check (it exists and may be written) and then fails the
    write with ENOSPC, as a disk that filled up during the recording does."""
    page = tmp_path / "move.html"
    code, out, err = record(tmp_path, capsys, "--csv", "/dev/full", "--plot", str(page))
    assert code == 2
    assert err.splitlines()[-1] == ("epos-link record: cannot write /dev/full: No space left on device; "
                                    f"wrote {page}")
    assert "Traceback" not in err and out.rstrip().endswith(f"wrote {page}")
    assert len(plot_panels(page.read_text())) == 2  # the recording is kept


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full (Linux)")
def test_a_png_on_a_full_disk_keeps_the_csv(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("matplotlib", reason="the PNG needs matplotlib")
    png, table = tmp_path / "move.png", tmp_path / "move.csv"
    png.symlink_to("/dev/full")  # matplotlib's own write fails
    code, _, err = record(tmp_path, capsys, "--csv", str(table), "--plot", str(png))
    assert code == 2 and "Traceback" not in err
    assert err.splitlines()[-1] == (f"epos-link record: cannot write {png}: No space left on device; "
                                    f"wrote {table}")
    rows = list(csv.reader(table.open()))
    assert rows[0][:2] == ["time [s]", "statusword"] and len(rows) > 1


def test_a_plot_backend_error_keeps_the_csv(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                            monkeypatch: pytest.MonkeyPatch) -> None:
    pytest.importorskip("matplotlib", reason="the pre-check wants matplotlib for an SVG")
    from epos_link.tools import plot

    class Broken:
        def savefig(self, *args: Any, **kwargs: Any) -> None:
            raise RuntimeError("the backend cannot draw this")

    monkeypatch.setattr(plot, "figure", lambda *a, **k: Broken())
    svg, page, table = tmp_path / "a.svg", tmp_path / "b.html", tmp_path / "c.csv"
    code, _, err = record(tmp_path, capsys, "--plot", str(svg), "--plot", str(page),
                          "--csv", str(table))
    assert code == 2 and "Traceback" not in err
    assert err.splitlines()[-1] == (f"epos-link record: cannot write {svg}: RuntimeError: the backend "
                                    f"cannot draw this; wrote {table}, {page}")
    assert table.exists() and page.exists() and not svg.exists()


def test_good_outputs_still_exit_0(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    table, page = tmp_path / "r.csv", tmp_path / "r.html"
    code, out, err = record(tmp_path, capsys, "--csv", str(table), "--plot", str(page))
    assert code == 0, err
    assert out.rstrip().endswith(f"wrote {table}, {page}") and table.exists() and page.exists()
