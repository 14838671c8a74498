"""The motor record's arithmetic and names (tcp_bridge.epics.record, .names): pure, no
caproto. Expected values follow epics-modules/motor motorRecord.cc as cited there."""
from __future__ import annotations

import sys

import pytest

from tcp_bridge.epics import fields as F
from tcp_bridge.epics import names
from tcp_bridge.epics.record import (Frame, Sample, alarm, live_fields, nint, runs_away,
                                     too_small, violates)
from tcp_bridge.tables.axes import ConfigError


def test_the_pure_modules_need_no_caproto_nor_sockets() -> None:
    import subprocess

    code = ("import sys, tcp_bridge.epics.record, tcp_bridge.epics.names, "
            "tcp_bridge.epics.fields, tcp_bridge.epics; "
            "print(sorted(m for m in ('caproto', 'asyncio', 'socket') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=60, check=True)
    assert out.stdout.strip() == "[]", out.stdout


def test_nint_rounds_halves_away_from_zero_as_motor_h() -> None:
    assert [nint(x) for x in (0.5, 1.49, -0.5, -1.5, 2.0)] == [1, 1, -1, -2, 2]


def test_user_and_dial_coordinates_and_limits_follow_dir_and_off() -> None:
    pos, neg = Frame(off=10.0, dir=1, mres=0.001), Frame(off=10.0, dir=-1, mres=0.001)
    assert pos.user(2.0) == 12.0 and neg.user(2.0) == 8.0
    assert neg.dial(neg.user(3.25)) == pytest.approx(3.25)
    assert pos.raw(1.2345) == 1235  # NINT(dial / MRES)
    assert pos.user_limits(5.0, -1.0) == (15.0, 9.0)
    assert neg.user_limits(5.0, -1.0) == (11.0, 5.0)  # HLM = -DLLM + OFF
    assert neg.dial_limit_of_user("HLM", 11.0) == ("DLLM", -1.0)
    assert pos.dial_limit_of_user("LLM", 9.0) == ("DLLM", -1.0)


@pytest.mark.parametrize("dval, ldvl, expected", [
    (5.0, 0.0, False), (10.5, 0.0, True), (-3.0, 0.0, True),
    (11.0, 12.0, False),  # outside, but moving back towards the range
    (13.0, 12.0, True),
])
def test_limit_violation(dval: float, ldvl: float, expected: bool) -> None:
    assert violates(dval, ldvl, 10.0, -2.0) is expected


def test_no_limits_when_both_dial_limits_are_zero() -> None:
    assert not violates(1e9, 0.0, 0.0, 0.0)


def test_too_small_compares_raw_positions() -> None:
    assert too_small(1.0004, 1.0, 0.001) and not too_small(1.0006, 1.0, 0.001)


@pytest.mark.parametrize("target, drbv, cdir, expected", [
    (0.5, 1.5, 1, True),  # behind a positive move: stop, then go back
    (3.0, 1.5, 1, False),  # ahead of it: the running move goes on
    (1.5015, 1.5, 1, False),  # within NTMF x RDBD (2 x 0.001)
    (1.497, 1.5, 1, True),  # just past it, beyond the deadband
    (2.5, 1.5, 0, True), (0.5, 1.5, 0, False),  # the same for a negative move
])
def test_the_new_target_monitor_stops_only_when_the_axis_runs_away_from_the_target(
        target: float, drbv: float, cdir: int, expected: bool) -> None:
    # motorRecord.cc process(): sign(RDIF) != CDIR and |DIFF| > NTMF x (|BDST| + RDBD)
    assert runs_away(target, drbv, cdir, mres=0.001, ntmf=2.0, bdst=0.0,
                     rdbd=0.001) is expected


def test_a_sample_makes_the_live_fields_msta_and_alarm() -> None:
    moving = Sample(statusword=0x0237, position=1.5, velocity=2.0, reached=0, switch=0)
    out = live_fields(moving, Frame(mres=0.001), dval=3.0, homed=True, problem=None,
                      last_direction=1)
    assert out["RBV"] == 1.5 and out["RRBV"] == 1500 and out["DIFF"] == 1.5
    assert out["MOVN"] == 1 and out["CNEN"] == "Enable" and out["EnableRBV"] == 1
    msta = out["MSTA"]
    assert msta & F.MSTA_MOVING and not msta & F.MSTA_DONE and msta & F.MSTA_HOMED
    assert msta & F.MSTA_DIRECTION and msta & F.MSTA_POSITION
    assert alarm(moving, None) == (0, 0) and out["MsgTxt"] == ""
    at_switch = Sample(statusword=0x0637, position=9.0, reached=1, switch=1, errors=1 << 6)
    out = live_fields(at_switch, Frame(dir=-1), dval=9.0, homed=False, problem=None,
                      last_direction=1)
    assert (out["RHLS"], out["RLLS"], out["HLS"], out["LLS"]) == (1, 0, 0, 1)
    assert out["MSTA"] & F.MSTA_PLUS_LS and out["MSTA"] & F.MSTA_DONE
    silent = Sample(failure="bus can1: device silent", silent=True)
    out = live_fields(silent, Frame(), dval=0.0, homed=False, problem=None, last_direction=1)
    assert "RBV" not in out and out["Connected"] == 0 and out["MSTA"] & F.MSTA_COMM_ERR
    assert alarm(silent, None) == (F.STAT_MENU.index("COMM"), 3)
    assert out["MsgTxt"] == "bus can1: device silent"
    fault = Sample(statusword=0x0218, position=0.0, reached=0)
    assert alarm(fault, None) == (F.STAT_MENU.index("STATE"), 2)
    assert alarm(Sample(statusword=0x0237, reached=1), "move: refused")[1] == 2


def test_record_names_and_their_mistakes() -> None:
    assert names.record_names("LAB:", [(1, None), (2, "sampleX")]) == \
        [(1, "LAB:m1"), (2, "LAB:sampleX")]
    with pytest.raises(ConfigError, match="used by axes 1 and 2"):
        names.record_names("LAB:", [(1, "m2"), (2, None)])
    with pytest.raises(ConfigError, match="only letters"):
        names.record_names("LAB.x", [(1, None)])
    with pytest.raises(ConfigError, match="longer than 60"):
        names.record_names("L" * 60, [(1, None)])


def test_the_environment_of_the_ca_server() -> None:
    assert names.interfaces({}) == ["127.0.0.1"]
    assert names.interfaces({"EPICS_CAS_INTF_ADDR_LIST": "10.1.2.5 127.0.0.1"}) == \
        ["10.1.2.5", "127.0.0.1"]
    with pytest.raises(ConfigError, match="not an IP address"):
        names.interfaces({"EPICS_CAS_INTF_ADDR_LIST": "eth0"})
    assert names.beacon_addresses({}, ["127.0.0.1"]) == [("127.0.0.1", 5065)]
    assert names.beacon_addresses({"EPICS_CAS_BEACON_PORT": "7000"}, ["127.0.0.1"]) == \
        [("127.0.0.1", 7000)]
    assert names.beacon_addresses({"EPICS_CAS_BEACON_ADDR_LIST": "10.1.2.255"},
                                  ["127.0.0.1"]) is None  # caproto's rule then
    assert names.beacon_addresses({}, ["10.1.2.5"]) is None
    assert names.server_port({}) == 5064
    with pytest.raises(ConfigError):
        names.server_port({"EPICS_CA_SERVER_PORT": "70000"})


def test_the_axis_table_takes_an_epics_prefix_and_names(tmp_path) -> None:  # type: ignore[no-untyped-def]
    from tcp_bridge.tables.axes import AxisTable

    path = tmp_path / "axes.toml"
    path.write_text('[epics]\nprefix = "LAB:"\n[bus.can1]\nbackend = "sim"\n'
                    '[[axis]]\nnode_id = 1\nepics_name = "x"\n')
    table = AxisTable.load(path)
    assert table.epics_prefix == "LAB:" and table.axes[1].epics_name == "x"
    path.write_text('[epics]\nprefx = "LAB:"\n[bus.can1]\nbackend = "sim"\n[[axis]]\nnode_id = 1\n')
    with pytest.raises(ConfigError, match="did you mean 'prefix'"):
        AxisTable.load(path)
