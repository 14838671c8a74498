"""A fake pysoem for the ``ethercat`` backend's unit tests (dependency injection: ``soem=``).

It has pysoem's shape as far as the backend uses it (``Master``, its slaves, the
exception classes, ``al_status_code_to_string``) and a minimal slave behind it:
an object dictionary, a PDO mapping in 1C12h/1C13h/1600h/1A00h (controlword,
mode and target position out; statusword and position in), the EtherCAT state,
and a drop-out switch. Every process-data and state call checks that no other
thread is inside those at the same time (:attr:`FakeMaster.overlaps` counts
violations); CoE transfers run beside them, as SOEM allows, and only count
overlapping each other (:attr:`FakeMaster.mailbox_overlaps`).
"""
from __future__ import annotations

import threading
import time
from typing import Any, Dict, List, Optional, Tuple

INIT_STATE, PREOP_STATE, SAFEOP_STATE, OP_STATE, STATE_ERROR, STATE_ACK = 1, 2, 4, 8, 16, 16
NONE_STATE = 0


class SdoError(Exception):
    def __init__(self, slave_pos: int, index: int, subindex: int, abort_code: int, desc: str):
        super().__init__(slave_pos, index, subindex, abort_code, desc)
        self.slave_pos, self.abort_code, self.desc = slave_pos, abort_code, desc


class WkcError(Exception):
    def __init__(self, message: str = "", wkc: int = 0):
        super().__init__(message, wkc)
        self.message, self.wkc = message, wkc


class MailboxError(Exception):
    def __init__(self, slave_pos: int, error_code: int, desc: str):
        super().__init__(slave_pos, error_code, desc)
        self.slave_pos, self.error_code, self.desc = slave_pos, error_code, desc


class ConfigMapError(Exception):
    def __init__(self, error_list: List[Exception]):
        self.error_list = error_list


class PacketError(Exception):
    def __init__(self, slave_pos: int, error_code: int):
        super().__init__(slave_pos, error_code)
        self.slave_pos, self.error_code = slave_pos, error_code


AL_TEXTS = {0x001B: "Sync manager watchdog", 0x0011: "Invalid requested state change"}


def al_status_code_to_string(code: int) -> str:
    return AL_TEXTS.get(code, "Unknown AL status code")


def mapping(index: int, sub: int, bits: int) -> int:
    return index << 16 | sub << 8 | bits


class FakeSlave:
    """RxPDO 1600h: 6040h (16) 6060h (8) 607Ah (32); TxPDO 1A00h: 6041h (16) 6064h (32)."""

    def __init__(self, master: "FakeMaster", position: int) -> None:
        self._master = master
        self.position = position
        self.name = "EPOS4"
        self.man, self.id, self.rev = 0x000000FB, 0x69500000, 0x01700000
        self.state = INIT_STATE
        self.al_status = 0
        self.present = True
        self.ca_used = False
        self.complete_access = True  # the SII offers CA (pysoem: _disable_complete_access)
        self.sdo_delay = 0.0  # seconds every CoE transfer takes (a slave that answers late)
        self.lose = 0  # the next this many CoE transfers get no answer (frames lost on the line)
        self.lose_reads = dict(master.lose_reads)  # index: its next this many reads get none
        self.transfers = 0  # CoE transfers tried
        self.ca_padding = True  # False: its CA answers leave out the padding byte (issue 31)
        self.recovered = 0
        self.resets = 0  # requests of INIT (the bridge's "NMT reset")
        self.acks = 0  # error indications acknowledged (AL Control with the Ack bit)
        self.od: Dict[Tuple[int, int], bytes] = {
            (0x1000, 0): (0x00020192).to_bytes(4, "little"), (0x1008, 0): b"EPOS4",
            (0x1018, 1): self.man.to_bytes(4, "little"), (0x1018, 2): self.id.to_bytes(4, "little"),
            (0x1C12, 0): b"\x01", (0x1C12, 1): (0x1600).to_bytes(2, "little"),
            (0x1C13, 0): b"\x01", (0x1C13, 1): (0x1A00).to_bytes(2, "little"),
            (0x1600, 0): b"\x03", (0x1600, 1): mapping(0x6040, 0, 16).to_bytes(4, "little"),
            (0x1600, 2): mapping(0x6060, 0, 8).to_bytes(4, "little"),
            (0x1600, 3): mapping(0x607A, 0, 32).to_bytes(4, "little"),
            (0x1A00, 0): b"\x02", (0x1A00, 1): mapping(0x6041, 0, 16).to_bytes(4, "little"),
            (0x1A00, 2): mapping(0x6064, 0, 32).to_bytes(4, "little"),
            (0x6040, 0): b"\0\0", (0x6060, 0): b"\x01", (0x607A, 0): b"\0\0\0\0",
            (0x6041, 0): (0x0250).to_bytes(2, "little"), (0x6064, 0): (1234).to_bytes(4, "little"),
            (0x6081, 0): (1000).to_bytes(4, "little"), (0x6061, 0): b"\x01",
            (0x60FF, 0): bytes(4), (0x606C, 0): bytes(4), (0x6067, 0): (10).to_bytes(4, "little"),
            (0x607D, 1): bytes(4), (0x6085, 0): bytes(4), (0x6065, 0): bytes(4),
            (0x60FD, 0): bytes(4),
        }
        self._output = bytearray(7)
        self.received: List[bytes] = []  # every output image the slave got in OP
        self.watchdog: Optional[float] = None

    # process data
    @property
    def output(self) -> bytes:
        return bytes(self._output)

    @output.setter
    def output(self, data: bytes) -> None:
        self._output[:] = data

    @property
    def input(self) -> bytes:
        return self.od[(0x6041, 0)] + self.od[(0x6064, 0)]

    def exchange(self) -> int:
        if not self.present:
            return 0
        if self.state == OP_STATE:
            self.received.append(bytes(self._output))
            self.od[(0x6040, 0)] = bytes(self._output[0:2])
        return 3 if self.state == OP_STATE else 0

    # mailbox: apart from the process data (SOEM's frame index buffers); transfers overlapping
    # each other are counted in master.mailbox_overlaps
    def _disable_complete_access(self) -> None:
        self.complete_access = False

    def eeprom_read(self, word: int, timeout: int = 20000) -> bytes:
        raise WkcError("no SII in the fake", 0)

    def sdo_read(self, index: int, subindex: int, size: int = 0, ca: bool = False, *,
                 release_gil: Optional[bool] = None) -> bytes:
        with self._master.mailbox():
            self.ca_used |= ca
            if self.sdo_delay:
                time.sleep(self.sdo_delay)
            self.transfers += 1
            if self.lose or self.lose_reads.get(index):
                if self.lose:
                    self.lose -= 1
                else:
                    self.lose_reads[index] -= 1
                raise WkcError("lost", -2)
            if not self.present:
                raise WkcError("no answer", 0)
            if (index, subindex) not in self.od:
                raise SdoError(self.position, index, subindex, 0x06020000, "Object does not exist")
            if ca:  # complete access: subindex 0 padded to 16 bits, then 1..n (ETG.1000.6)
                count = self.od[(index, 0)][:1]
                return count + b"\0" * self.ca_padding + b"".join(
                    self.od[(index, n)] for n in range(1, count[0] + 1))
            return self.od[(index, subindex)]

    def sdo_write(self, index: int, subindex: int, data: bytes, ca: bool = False, *,
                  release_gil: Optional[bool] = None) -> None:
        with self._master.mailbox():
            self.ca_used |= ca
            if self.sdo_delay:
                time.sleep(self.sdo_delay)
            self.transfers += 1
            if self.lose:
                self.lose -= 1
                raise WkcError("lost", -2)
            if not self.present:
                raise WkcError("no answer", 0)
            if (index, subindex) == (0x1000, 0):
                raise SdoError(self.position, index, subindex, 0x06010002, "read only")
            self.od[(index, subindex)] = bytes(data)

    def set_watchdog(self, kind: str, ms: float) -> None:
        self.watchdog = ms

    def write_state(self) -> int:
        with self._master.inside():
            if self.present and self.state == INIT_STATE:
                self.resets += 1
            elif self.present and self.state == OP_STATE:
                self.al_status = 0
            elif self.present and self.state & STATE_ACK:  # the error acknowledged
                self.state, self.al_status = self.state & 0x0F, 0
                self.acks += 1
            return 1

    def reconfig(self, timeout: int) -> int:
        """As SOEM's ecx_reconfig_slave on a strict slave: INIT, then PREOP and SAFEOP;
        with its error indication set (not acknowledged) the slave goes down to INIT
        but refuses every higher state (ETG.1000.6 6.4.1; the simulated ESC and the
        slave stack code do the same), and the state read back is returned."""
        with self._master.inside():
            if self.present:
                self.state = INIT_STATE | STATE_ERROR if self.state & STATE_ERROR else SAFEOP_STATE
            return self.state

    def recover(self, timeout: int) -> int:
        with self._master.inside():
            self.recovered += 1
            if self.present:
                self.state = INIT_STATE
                return 1
            return 0

    def drop_out(self) -> None:
        """The slave's watchdog tripped, as on a cable pulled and plugged again."""
        self.state, self.al_status = SAFEOP_STATE | STATE_ERROR, 0x001B

    def drop_to_init(self) -> None:
        """The slave is back in INIT with its error flag (a restart that failed, or a
        master that took it down without acknowledging its error)."""
        self.state, self.al_status = INIT_STATE | STATE_ERROR, 0x0011


class DriveSlave(FakeSlave):
    """A slave with a CiA 402 drive behind it (tcp_bridge.backends.instant.FakeNode): its
    mailbox is the drive's SDO server; in OP each changed output object is written to
    the drive, and the inputs are the drive's statusword and position.
    RxPDO 1600h: 6040h 6060h 607Ah 60FFh; TxPDO 1A00h: 6041h 6064h 6061h."""

    RX = ((0x6040, 16), (0x6060, 8), (0x607A, 32), (0x60FF, 32))
    TX = ((0x6041, 16), (0x6064, 32), (0x6061, 8))

    def __init__(self, master: "FakeMaster", position: int) -> None:
        from tcp_bridge.backends.instant import FakeNode

        super().__init__(master, position)
        self.drive = FakeNode(position)
        self.drive.values[(0x1000, 0)] = 0x00020192
        self.drive.values[(0x1008, 0)] = 0
        for n, (index, bits) in enumerate(self.RX, start=1):
            self.od[(0x1600, n)] = mapping(index, 0, bits).to_bytes(4, "little")
        for n, (index, bits) in enumerate(self.TX, start=1):
            self.od[(0x1A00, n)] = mapping(index, 0, bits).to_bytes(4, "little")
        self.od[(0x1600, 0)], self.od[(0x1A00, 0)] = bytes([len(self.RX)]), bytes([len(self.TX)])
        self._output = bytearray(11)
        self._applied = bytes(11)

    def _map(self, key: Tuple[int, int]) -> bool:
        return key[0] in (0x1C12, 0x1C13, 0x1600, 0x1A00) or key in ((0x1018, 1), (0x1018, 2))

    def sdo_read(self, index: int, subindex: int, size: int = 0, ca: bool = False, *,
                 release_gil: Optional[bool] = None) -> bytes:
        if self._map((index, subindex)):
            return super().sdo_read(index, subindex, size, ca)
        with self._master.mailbox():
            self.ca_used |= ca
            if self.sdo_delay:
                time.sleep(self.sdo_delay)
            return self._drive_sdo(lambda: self.drive.upload(index, subindex))

    def sdo_write(self, index: int, subindex: int, data: bytes, ca: bool = False, *,
                  release_gil: Optional[bool] = None) -> None:
        with self._master.mailbox():
            self.ca_used |= ca
            if self.sdo_delay:
                time.sleep(self.sdo_delay)
            self._drive_sdo(lambda: self.drive.download(index, subindex, bytes(data)))

    def _drive_sdo(self, transfer: Any) -> Any:
        from canopen.sdo.exceptions import SdoAbortedError

        if not self.present:
            raise WkcError("no answer", 0)
        try:
            return transfer()
        except SdoAbortedError as exc:
            raise SdoError(self.position, 0, 0, exc.code, str(exc)) from None

    @property
    def input(self) -> bytes:
        return b"".join(self.drive.upload(index, 0) for index, _ in self.TX)

    def exchange(self) -> int:
        if not self.present:
            return 0
        if self.state != OP_STATE:
            return 0
        out, offset = bytes(self._output), 0
        for index, bits in self.RX:
            size = bits // 8
            if out[offset:offset + size] != self._applied[offset:offset + size]:
                self.drive.download(index, 0, out[offset:offset + size])
            offset += size
        self._applied = out
        self.received.append(out)
        return 3


class FakeMaster:
    """``pysoem.Master`` over :class:`FakeSlave` s; ``count`` slaves, ``fail_open`` raises."""

    count = 2
    fail_open = False
    lose_reads: Dict[int, int] = {}  # each new slave's lose_reads (frames lost at set-up)
    instances: List["FakeMaster"] = []

    def __init__(self) -> None:
        self.slaves: List[FakeSlave] = []
        self.state = INIT_STATE
        self.sdo_read_timeout = self.sdo_write_timeout = 700000
        self.overlaps = 0
        self.mailbox_overlaps = 0
        self.config_maps = 0
        self.fail_ca_map = False  # config_map fails while a slave uses CA (issue 31)
        self.closed = False
        self.link = True
        self._busy = threading.Lock()
        self._mailbox = threading.Lock()
        type(self).instances.append(self)

    def mailbox(self) -> Any:
        master = self

        class Transfer:
            def __enter__(self) -> None:
                if not master._mailbox.acquire(blocking=False):
                    master.mailbox_overlaps += 1
                    master._mailbox.acquire()

            def __exit__(self, *exc: Any) -> None:
                master._mailbox.release()
        return Transfer()

    def inside(self) -> Any:
        master = self

        class Inside:
            def __enter__(self) -> None:
                if not master._busy.acquire(blocking=False):
                    master.overlaps += 1
                    master._busy.acquire()

            def __exit__(self, *exc: Any) -> None:
                master._busy.release()
        return Inside()

    def open(self, ifname: str) -> None:
        if self.fail_open:
            raise ConnectionError(f"could not open interface {ifname}")

    slave_class: Any = FakeSlave

    def config_init(self) -> int:
        self.slaves = [self.slave_class(self, p) for p in range(1, self.count + 1)]
        for s in self.slaves:
            s.state = PREOP_STATE
        return len(self.slaves) or -1

    def config_map(self) -> int:
        self.config_maps += 1
        if self.fail_ca_map and any(s.complete_access for s in self.slaves):
            raise ConfigMapError([PacketError(1, 1)])  # issue 31, KickCAT's slave
        for s in self.slaves:
            s.state = SAFEOP_STATE
        return 11 * len(self.slaves)

    @property
    def expected_wkc(self) -> int:
        return 3 * len(self.slaves)

    def state_check(self, state: int, timeout: int = 50000) -> int:
        with self.inside():
            return min((s.state for s in self.slaves), default=NONE_STATE)

    def read_state(self) -> int:
        with self.inside():
            for s in self.slaves:
                if not s.present:
                    s.state = NONE_STATE
            return min((s.state for s in self.slaves), default=NONE_STATE)

    def write_state(self) -> int:
        with self.inside():
            for s in self.slaves:
                if s.present and s.state & 0x0F in (SAFEOP_STATE, OP_STATE) and not s.state & 0x10:
                    s.state = self.state
            return 1

    def send_processdata(self, *, release_gil: Optional[bool] = None) -> int:
        with self.inside():
            self._wkc = sum(s.exchange() for s in self.slaves) if self.link else -1
            return 1

    def receive_processdata(self, timeout: int = 2000, *,
                            release_gil: Optional[bool] = None) -> int:
        with self.inside():
            return self._wkc

    def close(self) -> None:
        self.closed = True


class FakeSoem:
    """The module object given to the backend as ``soem=``."""

    SdoError, WkcError, MailboxError, PacketError = SdoError, WkcError, MailboxError, PacketError
    ConfigMapError = ConfigMapError

    def __init__(self, count: int = 2, fail_open: bool = False, drives: bool = False) -> None:
        class Master(FakeMaster):
            pass
        Master.count, Master.fail_open = count, fail_open
        Master.slave_class = DriveSlave if drives else FakeSlave
        Master.instances = []
        self.Master = Master
        self.masters = Master.instances

    @staticmethod
    def al_status_code_to_string(code: int) -> str:
        return al_status_code_to_string(code)
