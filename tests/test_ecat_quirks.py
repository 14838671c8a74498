"""Issue 31: the simulated EPOS4 EtherCAT slave as strict as the device, and as quirky as
independent slave stacks; the pure helpers of :mod:`tcp_bridge.backends.ethercat_slaves`.

Golden bytes: the abort's CoE header and the Complete Access layout come from SOEM's
``ecx_SDOread`` / ``ec_PDOassignt`` (``uint8 n; uint8 nu1; uint16 index[]``) and
ETG.1000.6 5.6.2, not from our encoder.
"""
from __future__ import annotations

import struct
from typing import Any, Dict, List

import pytest

from epos_link.simulator.ethercat.coe import MBX_COE, SdoServer
from epos_link.simulator.ethercat.drive_app import EthercatDrive
from epos_link.simulator.ethercat.quirks import QuirkError, Quirks, parse_quirks
from tcp_bridge.backends import ethercat_slaves as info


def coe(server: SdoServer, request: bytes) -> bytes:
    kind, reply = server.handle(MBX_COE, struct.pack("<H", 2 << 12) + request)
    assert kind == MBX_COE
    return reply


def test_an_abort_names_the_sdo_request_service_as_soem_expects() -> None:
    server = EthercatDrive(1).slave.sdo
    reply = coe(server, struct.pack("<BHBI", 0x40, 0x1234, 0, 0))
    # CoE header 0x2000: service 2; then 0x80, index, subindex, 06020000h
    assert reply == bytes.fromhex("0020" "80" "3412" "00" "00000206")


@pytest.mark.parametrize("padding, answer", [
    (True, bytes.fromhex("0100" "0016")),   # n = 1, padding, 1600h
    (False, bytes.fromhex("01" "0016")),    # the padding byte left out (quirk ca-no-pad)
])
def test_complete_access_upload_of_the_pdo_assignment(padding: bool, answer: bytes) -> None:
    drive = EthercatDrive(1, quirks=Quirks(ca_padding=padding))
    reply = coe(drive.slave.sdo, struct.pack("<BHBI", 0x50, 0x1C12, 0, 0))  # 0x40 | CA bit
    size = 4 - ((reply[2] >> 2) & 3)
    assert reply[2] & 0x02 and reply[6:6 + size] == answer


def test_complete_access_download_is_refused() -> None:
    reply = coe(EthercatDrive(1).slave.sdo, struct.pack("<BHBI", 0x33, 0x1C12, 0, 0))
    assert reply[2] == 0x80 and struct.unpack_from("<I", reply, 6)[0] == 0x06010000


def test_a_missing_object_aborts_as_object_does_not_exist() -> None:
    drive = EthercatDrive(2, quirks=Quirks(missing=frozenset({0x6067})))
    reply = coe(drive.slave.sdo, struct.pack("<BHBI", 0x40, 0x6067, 0, 0))
    assert reply[2] == 0x80 and struct.unpack_from("<I", reply, 6)[0] == 0x06020000
    assert coe(drive.slave.sdo, struct.pack("<BHBI", 0x40, 0x6064, 0, 0))[2] == 0x43


def test_quirks_parse_and_refuse_with_one_line() -> None:
    quirks = parse_quirks(["2:ca-no-pad", "2:no-6067", "1:late=1.5", "1:no-ca"], 2)
    assert quirks[2] == Quirks(ca_padding=False, missing=frozenset({0x6067}))
    assert quirks[1] == Quirks(offer_ca=False, late=1.5)
    for bad, words in (("3:no-ca", "no slave 3"), ("2:fast", "unknown quirk"),
                       ("x", "POSITION:NAME"), ("1:no-6040", "controlword"),
                       ("1:late=-1", "0..60")):
        with pytest.raises(QuirkError, match=words):
            parse_quirks([bad], 2)


def test_a_store_is_answered_late_and_the_reply_waits_in_the_slave() -> None:
    drive = EthercatDrive(1, quirks=Quirks(late=1.0))
    store = struct.pack("<HBHBI", 2 << 12, 0x23, 0x1010, 1, 0x65766173)  # "save"
    read = struct.pack("<HBHBI", 2 << 12, 0x40, 0x1018, 1, 0)
    assert drive._reply_delay(store) == 1.0 and drive._reply_delay(read) == 0.0


def events_of(drive: EthercatDrive) -> List[Dict[str, Any]]:
    seen: List[Dict[str, Any]] = []
    drive.on_event = seen.append
    return seen


def enable(drive: EthercatDrive) -> None:
    for cw in (0x0006, 0x000F):
        drive._apply_outputs([(0x6040, 0, cw.to_bytes(2, "little"))])
    assert drive.drive.state.name == "OPERATION_ENABLED"


def test_enable_operation_in_quick_stop_active_is_transition_16() -> None:
    """605Ah = 6 (the EPOS4's default): a drive that quick-stopped by itself goes back up
    on the stale "enable operation" it keeps receiving (why the bridge must hold it)."""
    drive = EthercatDrive(1)
    enable(drive)
    drive._leave_op("watchdog")  # 6007h = 3: quick stop
    assert drive.drive.state.name == "QUICK_STOP_ACTIVE"
    assert drive.store.get_int(0x605A) == 6 and drive.store.get_int(0x6007) == 3
    drive._apply_outputs([(0x6040, 0, (0x000F).to_bytes(2, "little"))])
    assert drive.drive.state.name == "OPERATION_ENABLED"
    assert drive.read(0x6040, 0) == (0x000F).to_bytes(2, "little")  # the last one received


def test_the_controlword_is_given_to_the_drive_with_every_frame() -> None:
    from epos_link.simulator.ethercat.slave import LEVEL_OBJECTS

    assert (0x6040, 0) in LEVEL_OBJECTS


def test_the_quick_stop_input_holds_the_drive_while_it_is_active() -> None:
    drive = EthercatDrive(1)
    seen = events_of(drive)
    enable(drive)
    drive.write(0x2100, 0, (9).to_bytes(4, "little"))
    assert drive.drive.state.name == "QUICK_STOP_ACTIVE"
    drive._apply_outputs([(0x6040, 0, (0x000F).to_bytes(2, "little"))])  # a stale enable
    assert drive.drive.state.name == "QUICK_STOP_ACTIVE"
    drive.write(0x2100, 0, (10).to_bytes(4, "little"))  # released: stays (605Ah = 6)
    assert drive.drive.state.name == "QUICK_STOP_ACTIVE"
    kinds = [e["event"] for e in seen]
    assert kinds.count("quick_stop_input") == 1 and "quick_stop_release" in kinds
    assert seen[-2]["event"] == "outputs" and seen[-2]["cw"] == 0x000F  # as the master sent


def test_outputs_earn_no_working_counter_outside_op() -> None:
    """The firmware deactivates SM2 through the PDI outside OP (SSC StopOutputHandler):
    a master sees the drop-out as a short working counter."""
    slave = EthercatDrive(1).slave
    assert slave.esc.sm_deactivated[2]


# -- tcp_bridge.backends.ethercat_slaves ----------------------------------------------------


def od(values: Dict[Any, bytes]) -> Any:
    class Abort(Exception):
        code = 0x06020000

    def upload(index: int, sub: int) -> bytes:
        if (index, sub) not in values:
            raise Abort()
        return values[(index, sub)]
    return upload


ASSIGN = {(0x1C12, 0): b"\x01", (0x1C12, 1): b"\x00\x16"}


def test_ca_problem_names_the_missing_padding_byte() -> None:
    expected = info.expected_ca(od(ASSIGN), 0x1C12)
    assert expected == bytes.fromhex("01000016")
    assert info.ca_problem(expected, expected) is None
    assert "without the padding byte" in str(info.ca_problem(bytes.fromhex("010016"), expected))
    assert "differs" in str(info.ca_problem(b"\x02", expected))


def test_missing_objects_are_one_line_each_naming_what_they_disable() -> None:
    values = {key: b"\0" for key in list(info.MANDATORY) + list(info.OPTIONAL)}
    del values[(0x6067, 0)], values[(0x60FF, 0)]
    missing = info.missing_objects(od(values), lambda exc: getattr(exc, "code", None))
    lines = [info.missing_line(2, *m) for m in missing]
    assert lines == ["slave 2: no 60FFh (mandatory): target velocity: no velocity move (S00=3)",
                     "slave 2: no 6067h (optional): position window: R82 of a cyclic axis "
                     "uses the axis table's position_window instead; R13 is NAK"]


def test_other_failures_are_not_missing_objects() -> None:
    def timeout(index: int, sub: int) -> bytes:
        raise TimeoutError
    assert info.missing_objects(timeout, lambda exc: None) == []


def test_the_sii_coe_details_byte() -> None:
    from epos_link.simulator.ethercat.sii import build_sii

    for ca in (True, False):
        image = build_sii(1, ca=ca)
        details = info.sii_coe_details(
            lambda word: int.from_bytes(image[2 * word:2 * word + 2], "little"))
        assert details is not None and bool(details & info.COE_DETAILS_CA) is ca
