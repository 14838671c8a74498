"""The table of ``epos-link watch`` (epos_link/tools/watch_table.py): widths, decoding,
age and rate from times the test gives, and that the module stays pure."""
from __future__ import annotations

import re
import subprocess
import sys

import pytest

from epos_link.tools.watch_table import (LINK_DOWN, RATE_WINDOW, Layout, Row, Watched, columns, essential, fit,
                                         fit_value, format_age, format_rate, format_value, link_cause, render,
                                         unit_of, velocity_unit)

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
    # nothing tried for longer than the window: no rate known
    assert row.rate(102.5 + RATE_WINDOW + 0.1) is None
    assert row.reads == 11


def test_rate_counts_successful_reads_and_falls_to_zero_while_reads_fail() -> None:
    """A dead link: reads go on being tried, every 0.25 s, and fail. The rate falls
    and is 0.0/s once the window holds no success; the value's age goes on growing."""
    row = Row(POSITION)
    for i in range(11):
        row.reading(1000 + i, 100.0 + 0.25 * i)  # the last value, 1010, read at 102.5
    assert row.rate(102.5) == pytest.approx(4.0)
    rates = []
    for i in range(1, 41):  # ten seconds of failures
        now = 102.5 + 0.25 * i
        row.failure(LINK_DOWN, now)
        rates.append(row.rate(now))
        assert row.age(now) == pytest.approx(now - 102.5)  # from the last good value
    assert rates[0] == pytest.approx(10 / 2.75)  # ten successes over 100.25..102.75
    assert all(b <= a for a, b in zip(rates, rates[1:]))  # falling...
    assert rates[-1] == 0.0 and format_rate(rates[-1]) == "0.0/s"  # ...to 0
    assert row.shown_value() == "! link down"
    row.reading(1010, 113.0)  # back: the same value, so the age still counts from 102.5
    assert row.shown_value() == "1010" and row.age(113.0) == pytest.approx(10.5)
    # one success since the last read tried before the window (at 107.75)
    assert row.rate(113.0) == pytest.approx(1 / 5.25)
    for i in range(1, 41):
        row.reading(1010, 113.0 + 0.25 * i)
    assert row.rate(123.0) == pytest.approx(4.0)


def test_a_period_longer_than_the_window_still_has_a_rate() -> None:
    row = Row(POSITION)
    for i in range(4):
        row.reading(i, 10.0 * i)
    assert row.rate(30.0) == pytest.approx(0.1)


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
    assert columns(["Modes of operation display"], 65, 80, 6) == Layout(12, 25)
    lines = render(rows_of_a_drive(), 1.0, 80)
    assert lines[1] == "0x6041/0x00  Statusword    0x0637 operation enabled~               1.0s    2.0/s"
    assert lines[2] == "0x6061/0x00  Modes of op~  3 profile velocity (pv)                 1.0s    2.0/s"
    # wide enough: the whole name
    assert columns(["Modes of operation display"], 65, 120, 6) == Layout(26, 51)
    assert columns(["Modes of operation display"], 65, 200, 6) == Layout(26, 65)  # no wider than the values


# -- a number is never cut ---------------------------------------------------------------------


def test_the_first_word_is_the_part_never_cut() -> None:
    assert essential("1867234") == 7
    assert essential("0x0437 operation enabled, voltage enabled") == len("0x0437")
    assert essential("! 0x06020000 Object does not exist error") == len("! 0x06020000")
    assert essential("! timeout") == len("! timeout")


@pytest.mark.parametrize("value, width, shown", [
    ("1867234", 10, "1867234   "),
    ("1867234", 7, "1867234"),
    ("1867234", 6, "######"),  # never 18672~
    ("0x0437 operation enabled, voltage enabled, target reached", 44, "0x0437 operation enabled, voltage enabled~  "),
    ("0x0437 operation enabled, voltage enabled, target reached", 30, "0x0437 operation enabled~     "),
    ("0x0040 switch on disabled", 20, "0x0040~             "),  # never "switch on~", another state
    ("0x0040 switch on disabled", 7, "0x0040~"),
    ("0x0040 switch on disabled", 6, "0x0040"),
    ("0x0040 switch on disabled", 5, "#####"),
    ("! 0x06020000 Object does not exist error", 20, "! 0x06020000~       "),
])
def test_a_value_is_cut_only_after_its_number_or_a_comma(value: str, width: int, shown: str) -> None:
    assert fit_value(value, width) == shown


def moving_drive() -> list[Row]:
    """The screen of the report: a drive in profile velocity mode, its position
    past six digits."""
    rows = [Row(STATUSWORD), Row(Watched(0x6061, 0, "Modes of operation display")), Row(POSITION),
            Row(Watched(0x606C, 0, "Velocity actual value", "rpm")), Row(Watched(0x1001, 0, "Error register")),
            Row(Watched(0x603F, 0, "Error code"))]
    for t in (0.0, 0.25, 0.5):
        for row, value in zip(rows, (0x0437, 3, 1867234 + int(t * 1000), 1000, 0, 0)):
            row.reading(value, t)
    return rows


@pytest.mark.parametrize("width", range(16, 141))
def test_every_number_is_whole_or_hashes_at_every_width(width: int) -> None:
    lines = render(moving_drive(), 1.0, width)
    assert all(len(line) <= width for line in lines)
    numbers = {"0x6041": "0x0437", "0x6061": "3", "0x6064": "1867734", "0x606C": "1000", "0x1001": "0x00",
               "0x603F": "0x0000"}
    for line in lines[1:]:
        number = numbers[line[:6]]
        assert re.search(rf"  ({re.escape(number)}~?|#+)( |$)", line[11:]), (width, line)


def test_at_60_columns_name_shrinks_and_rate_goes_before_a_number_is_cut() -> None:
    lines = render(moving_drive(), 1.0, 60)
    assert lines[0] == "OBJECT       NAME          VALUE           UNIT          AGE"
    assert lines[1] == "0x6041/0x00  Statusword    0x0437~                      1.0s"
    assert lines[2] == "0x6061/0x00  Modes of op~  3~                           1.0s"
    assert lines[3] == "0x6064/0x00  Position ac~  1867734         inc          0.5s"
    assert columns(["Modes of operation display"], 57, 60, 7) == Layout(12, 14, rate=False)


def test_the_docs_show_the_60_column_layout() -> None:
    from pathlib import Path

    page = (Path(__file__).resolve().parent.parent / "docs" / "epos-link.md").read_text(encoding="utf-8")
    block = "```text\n" + "\n".join(render(moving_drive()[:4], 1.0, 60)) + "\n```\n"
    assert block in page


@pytest.mark.parametrize("width, layout", [
    (50, Layout(12, 12, age=False, rate=False)),   # then AGE
    (40, Layout(7, 7, age=False, rate=False)),     # then NAME below its minimum...
    (35, Layout(0, 11, age=False, rate=False)),    # ...and away: UNIT stays with the number
    (30, Layout(8, 7, unit=False, age=False, rate=False)),  # then UNIT
    (16, Layout(0, 3, unit=False, age=False, rate=False)),  # not even that: #####
])
def test_the_order_columns_give_way_in(width: int, layout: Layout) -> None:
    assert columns(["Modes of operation display"], 57, width, 7) == layout


def test_without_units_the_unit_column_goes_first() -> None:
    assert columns(["Statusword"], 57, 60, 7, units=False) == Layout(12, 16, unit=False)
    assert columns(["Statusword"], 57, 60, 7, units=True) == Layout(12, 14, rate=False)
    assert columns(["Statusword"], 57, 200, 7, units=False) == Layout(12, 57)  # room: nothing goes


# -- a link that failed ------------------------------------------------------------------------


@pytest.mark.parametrize("message, cause", [
    ("cannot open socket://127.0.0.1:24571: Connection refused", "connection refused"),
    ("read from socket://127.0.0.1:24571 failed: [Errno 104] Connection reset by peer", "connection reset by peer"),
    ("socket://127.0.0.1:24571: connection closed by the peer (is another program connected to it? it serves "
     "one host at a time)", "connection closed by the peer (is another program connected to it? it serves one "
     "host at a time)"),
    ("socket://127.0.0.1:24571 is closed", "closed"),
    ("something else: EPOS4 gone", "something else: EPOS4 gone"),
])
def test_the_cause_of_a_link_failure_without_the_url(message: str, cause: str) -> None:
    assert link_cause(message, "socket://127.0.0.1:24571") == cause


def test_a_link_failure_is_one_status_line_never_cut() -> None:
    rows = moving_drive()
    for row in rows:
        row.failure(LINK_DOWN, 1.0)
    status = "! link down: connection refused; reconnecting at each read"
    lines = render(rows, 1.0, 130, "epos-link watch socket://127.0.0.1:24571 node 2", status)
    assert lines[1] == status and lines[2].startswith("OBJECT")
    # the row: no class name, no cause (the status line has it); AGE from the last value,
    # RATE the successes (two after the first of 0.0, 0.25, 0.5, 1.0) over 1 s
    assert re.fullmatch(r"0x6041/0x00  Statusword +! link down +1\.0s +2\.0/s", lines[3]), lines[3]
    narrow = render(rows, 1.0, 30, "", status)
    assert narrow[:3] == ["! link down: connection", "refused; reconnecting at each", "read"]
