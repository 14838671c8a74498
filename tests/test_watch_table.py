"""The table of ``epos-link watch`` (epos_link/tools/watch_table.py): widths, decoding,
age and rate from times the test gives, and that the module stays pure."""
from __future__ import annotations

import subprocess
import sys

import pytest

from epos_link.tools.watch_table import (RATE_WINDOW, Row, Watched, columns, fit, format_age, format_rate,
                                         format_value, render, unit_of, velocity_unit)

STATUSWORD = Watched(0x6041, 0, "Statusword")
POSITION = Watched(0x6064, 0, "Position actual value", "inc")


def test_the_module_is_pure() -> None:
    code = ("import sys\nbefore = set(sys.modules)\nimport epos_link.tools.watch_table\n"
            "new = set(sys.modules) - before\n"
            "print(','.join(m for m in ('time', 'socket', 'select', 'termios', 'threading', 'serial', "
            "'can', 'canopen') if m in new))\n")
    out = subprocess.run([sys.executable, "-S", "-c", f"import sys; sys.path[:0] = {sys.path!r}\n" + code],
                         capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""


# -- values -------------------------------------------------------------------------------


@pytest.mark.parametrize("index, value, shown", [
    # CiA 402-2 6.4.1.4 state coding: 0x0040 switch on disabled; 0x0637 operation
    # enabled with voltage enabled (4), remote (9), target reached (10)
    (0x6041, 0x0040, "0x0040 switch on disabled"),
    (0x6041, 0x0637, "0x0637 operation enabled, voltage enabled, remote, target reached"),
    (0x6041, 0x0008, "0x0008 fault"),
    (0x6061, 3, "3 profile velocity (pv)"),
    (0x6060, 1, "1 profile position (pp)"),
    (0x6061, -2, "-2 manufacturer-specific"),
    (0x6061, 5, "5 reserved"),
    (0x1001, 0x00, "0x00"),
    (0x1001, 0x11, "0x11 generic, communication"),  # CiA 301 7.5.2.2 bits 0 and 4
    (0x603F, 0x0000, "0x0000 No error"),
    (0x603F, 0x8611, "0x8611 Following error"),
    (0x6064, -1234, "-1234"),
])
def test_values_are_decoded_where_a_standard_says_what_they_mean(index: int, value: int, shown: str) -> None:
    assert format_value(index, 0, value) == shown


def test_other_values() -> None:
    assert format_value(0x1008, 0, "EPOS4") == '"EPOS4"'
    assert format_value(0x1018, 4, 1577058306) == "1577058306"
    assert format_value(0x2000, 0, b"\x01\xab") == "01 AB"
    assert format_value(0x2000, 0, b"") == "(empty)"
    assert format_value(0x2000, 0, 1.5) == "1.5"
    assert format_value(0x2000, 0, True) == "True"
    assert format_value(0x6041, 1, 0x40) == "64"  # a subindex of 6041h is not the statusword


def test_units() -> None:
    # 60A9h: prefix byte, then revolution (B4h) per minute (47h); maxon's prefixes 10^0..10^-3
    assert velocity_unit(0x00B44700) == "rpm"
    assert velocity_unit(0xFFB44700) == "0.1 rpm"
    assert velocity_unit(0xFDB44700) == "0.001 rpm"
    assert velocity_unit(0x01B44700) == "?"
    assert velocity_unit(0x00B44701) == "?"
    assert unit_of(0x6064, 0, "rpm") == "inc"
    assert unit_of(0x606C, 0, "0.01 rpm") == "0.01 rpm"
    assert unit_of(0x60FF, 0, "rpm") == "rpm"
    assert unit_of(0x6041, 0, "rpm") == ""
    assert unit_of(0x6064, 1, "rpm") == ""


# -- age and rate, from an injected clock ------------------------------------------------------


def test_age_is_the_time_since_the_value_changed() -> None:
    row = Row(STATUSWORD)
    assert row.age(5.0) is None and format_age(row.age(5.0)) == "-"
    row.reading(0x40, 10.0)
    row.reading(0x40, 11.0)
    row.reading(0x40, 12.0)
    assert row.age(12.5) == pytest.approx(2.5)  # the same value since 10.0
    row.reading(0x21, 13.0)
    assert row.age(13.25) == pytest.approx(0.25)
    row.failure("timeout", 14.0)
    assert row.shown_value() == "! timeout"  # a stale value is not shown as current
    assert row.age(14.0) == pytest.approx(1.0)
    row.reading(0x21, 15.0)
    assert row.shown_value() == "0x0021 ready to switch on" and row.age(15.0) == pytest.approx(2.0)
    assert row.age(None) == pytest.approx(2.0)  # as of the last read (--once)
    row.reading(0x21, 16.0)
    assert row.age(None) == pytest.approx(3.0) and row.age(20.0) == pytest.approx(7.0)


def test_rate_is_the_reads_per_second_over_the_window() -> None:
    row = Row(POSITION)
    row.reading(0, 100.0)
    assert row.rate(100.0) is None and format_rate(row.rate(100.0)) == "-"
    for i in range(1, 11):  # ten more reads, one every 0.25 s
        row.reading(i, 100.0 + 0.25 * i)
    assert row.rate(102.5) == pytest.approx(4.0)
    row.failure("timeout", 103.0)  # failures are not reads
    assert row.rate(103.0) == pytest.approx(4.0)
    # reads older than the window are forgotten; the rate needs two reads again
    assert row.rate(102.5 + RATE_WINDOW + 0.1) is None
    assert row.reads == 11


@pytest.mark.parametrize("age, shown", [(0.0, "0.0s"), (0.04, "0.0s"), (9.9, "9.9s"), (9.96, "10s"),
                                        (599.4, "599s"), (600, "10m"), (35000, "583m"), (36000, "10h"),
                                        (1e12, "99999h")])
def test_ages_fit_their_column(age: float, shown: str) -> None:
    assert format_age(age) == shown and len(shown) <= 6


@pytest.mark.parametrize("rate, shown", [(4.0, "4.0/s"), (123.45, "123.5/s"), (1500, "1500/s"),
                                         (1e9, "99999/s")])
def test_rates(rate: float, shown: str) -> None:
    assert format_rate(rate) == shown and len(shown) <= 7


# -- widths --------------------------------------------------------------------------------


def test_fit() -> None:
    assert fit("abc", 5) == "abc  "
    assert fit("abcdef", 4) == "abc~"
    assert fit("abc", 0) == ""


def rows_of_a_drive() -> list[Row]:
    rows = [Row(STATUSWORD), Row(Watched(0x6061, 0, "Modes of operation display")), Row(POSITION),
            Row(Watched(0x606C, 0, "Velocity actual value", "rpm"))]
    for t in (0.0, 0.5, 1.0):
        rows[0].reading(0x0637, t)
        rows[1].reading(3, t)
        rows[2].reading(int(1000 * t), t)
        rows[3].reading(1000, t)
    return rows


@pytest.mark.parametrize("width", [40, 60, 80, 100, 120, 160, 200])
def test_every_line_fits_the_width(width: int) -> None:
    lines = render(rows_of_a_drive(), 1.0, width, "epos-link watch socket://127.0.0.1:4001 node 2, every 0.5 s")
    assert len(lines) == 6
    assert all(len(line) <= width for line in lines)
    if width < 80:
        return  # cut at the right: the last columns fall off, nothing wraps
    # the columns stay where the header puts them, whatever the values
    value_at = lines[1].index("VALUE")
    assert all(line[value_at - 2:value_at] == "  " for line in lines[2:])


def test_a_wide_screen() -> None:
    # OBJECT 11, NAME 26 (the longest name), VALUE 65 (the longest value), UNIT 9, AGE 6,
    # RATE 7, two blanks between: VALUE starts at 41, UNIT at 108, AGE ends at 125, RATE
    # at 134, whatever room is left on the right.
    lines = render(rows_of_a_drive(), 1.0, 160)
    cells = [(line[:11], line[13:39].rstrip(), line[41:106].rstrip(), line[108:117].rstrip(),
              line[119:125].lstrip(), line[127:134].lstrip()) for line in lines]
    assert cells == [
        ("OBJECT     ", "NAME", "VALUE", "UNIT", "AGE", "RATE"),
        ("0x6041/0x00", "Statusword", "0x0637 operation enabled, voltage enabled, remote, target reached",
         "", "1.0s", "2.0/s"),
        ("0x6061/0x00", "Modes of operation display", "3 profile velocity (pv)", "", "1.0s", "2.0/s"),
        ("0x6064/0x00", "Position actual value", "1000", "inc", "0.0s", "2.0/s"),
        ("0x606C/0x00", "Velocity actual value", "1000", "rpm", "1.0s", "2.0/s"),
    ]
    assert all(len(line) == 134 for line in lines)
    assert all(line[11:13] + line[39:41] + line[106:108] + line[117:119] + line[125:127] == " " * 10
               for line in lines)


def test_the_value_column_grows_and_never_shrinks() -> None:
    row = Row(STATUSWORD)
    row.reading(0x0040, 0.0)
    narrow = render([row], 0.0, 200)
    assert narrow[1].startswith("0x6041/0x00  Statusword    0x0040 switch on disabled  ")  # NAME_MIN 12
    row.reading(0x0637, 1.0)
    row.reading(0x0040, 2.0)
    wide = render([row], 2.0, 200)
    assert len(wide[1]) == len(narrow[1]) + len("0x0637 operation enabled, voltage enabled, remote, target reached") \
        - len("0x0040 switch on disabled")


def test_a_narrow_screen_shortens_names_before_values() -> None:
    name, value = columns(["Modes of operation display"], 65, 80)
    assert (name, value) == (12, 25)
    lines = render(rows_of_a_drive(), 1.0, 80)
    assert lines[1] == "0x6041/0x00  Statusword    0x0637 operation enabled~               1.0s    2.0/s"
    assert lines[2] == "0x6061/0x00  Modes of op~  3 profile velocity (pv)                 1.0s    2.0/s"
    # wide enough: the whole name
    assert columns(["Modes of operation display"], 65, 120) == (26, 51)
    assert columns(["Modes of operation display"], 65, 200) == (26, 65)  # no wider than the values
