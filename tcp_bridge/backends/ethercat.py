"""``ethercat``: EtherCAT slaves with CoE (an EPOS4 EtherCAT) through pysoem (SOEM).

Bus options (``[bus.ethercat]``, bus offset 1000000 of PSI spec 3.3; an axis's
``node_id`` is the slave's position along the bus, 1 = the first after the card)::

    backend = "ethercat"
    interface = "eth1"     # the network card the slaves hang on (ip link)
    cycle_ms = 4           # the process-data cycle, 1..100 ms
    watchdog_ms = 100      # the slaves' process-data (SM) watchdog
    sdo_timeout = 0.3      # seconds per CoE SDO transfer (any length: the cycle runs on)
    op_timeout = 3.0       # seconds for every slave to reach OP at opening

Opening (ETG.1000.6 6.4, the EtherCAT state machine): the card is opened
(raw Ethernet frames: root or CAP_NET_RAW), ``config_init()`` finds the slaves
and reads their identity from the SII (vendor, product code, revision: the
1018h values), ``config_map()`` builds the I/O map from each slave's PDO
assignment (the slaves are SAFEOP). When that fails (a ``ConfigMapError``, SAFEOP
not reached, or an I/O map that does not match a slave's own PDO objects) the
slaves are configured once more with SDO Complete Access turned off
(:mod:`.ethercat_slaves` says why; logged). Then the slaves' process-data
watchdog is set, each slave's PDO layout is read (:mod:`.ethercat_pdo`), the
objects the bridge needs are looked up (a missing one is one log line naming
slave, object and what it disables), the cycle starts (:mod:`.ethercat_cycle`)
and **every output of every slave follows its drive** (:mod:`.ethercat_hold`):
the controlword keeps the state the statusword shows, 607Ah = 6064h, 60FFh = 0,
6060h = 6061h, from the inputs of the cycles run in SAFE-OP (other mapped
outputs start as the drive's values read by SDO; torque and offsets as 0).
Only then is OP requested. A new bridge never sends the last command of a
dead one, which an SDO read of 6040h would give back. A slave that does not
reach OP is logged with its AL status code and is *lost* (a silent node) until
the recovery brings it back, again with outputs that follow its drive; a
cyclic run on a slave that drops out ends (logged, R82 reads 0).

The node interface is canopen's, as on every backend (``node.sdo.upload/download``,
``node.nmt``), so the command layer and the motion rules are the CAN ones:

* an object mapped into the slave's **outputs** (RxPDO: controlword 6040h,
  target position 607Ah, ... whatever the slave maps) is written into the
  output image, not by SDO: the slave takes it from the process data and would
  overwrite an SDO write with the next cycle. The download returns once two
  cycles have carried it (the one in flight may have left before the write).
  Its upload answers the image.
* an object mapped into the **inputs** (TxPDO: statusword 6041h, position
  6064h, ...) is read from the first cycle completed after the request.
* every other object goes by CoE SDO, expedited or segmented as SOEM chooses
  by size, always **without Complete Access** (``ca=False``): some slaves
  mishandle it (ETG.1000.6 5.6.2.1.1 leaves it optional). A transfer holds
  the mailbox, not the cycle (:mod:`.ethercat_cycle` rule 1): a store of
  parameters (1010h) taking seconds delays no cycle; ``sdo_timeout`` bounds it.

Errors, as on the other backends (:mod:`tcp_bridge.bus.sdo` classifies them)::

    canopen SdoAbortedError(code)       the slave's SDO abort code (pysoem SdoError),
                                        answered NAK with the code and its text
    SlaveUnreachable                    (a canopen SdoCommunicationError) the slave is
                                        lost, not in OP (with its AL status code and
                                        text), or its mailbox did not answer: a silent node
    LinkDown (BusUnavailable, OSError)  no frame comes back: the bus's device is silent
    NmtError                            NMT reset node asked of a slave (no NMT here)

Cyclic set-points (for internal axes in CSP, the bridge computing the profile):
:meth:`EthercatNode.pdo_write` / :meth:`EthercatNode.cyclic_target` put a value
into the output image without waiting (it goes out with the next cycle);
:meth:`EthercatNode.pdo_read` reads the newest input (or output) value;
:meth:`EthercatBackend.add_cycle_hook` calls a function at the start of every
cycle, on the cycle thread, before the outputs are sent. Internal axes in CSP
(``cyclic = "csp"``) use them: :mod:`.ethercat_csp` makes each set-point on the
cycle that sends it; the slaves' SM watchdog (``watchdog_ms``) is what stops the
drives when the bridge dies, so no heartbeat is needed (or accepted) here.

**Chosen** (CoE has no NMT; ETG.1000.6 6.4 has the EtherCAT state machine
instead): ``nmt.state = "OPERATIONAL"`` makes the next cycle look at the
slave's state and ask for OP if needed; ``"RESET"`` (S16, and an enable after
a power cycle, :mod:`tcp_bridge.motion`) takes the slave to INIT, and the
recovery brings it back through PREOP and SAFEOP (its PDO configuration
written again) to OP; meanwhile it is a silent node, as a CANopen node is
while it boots. The drive's application is not reset by that: after a real
power cycle its RAM values are the defaults anyway, and the bridge writes its
parameters back at the next enable. Other NMT states are refused (NmtError).
"""
from __future__ import annotations

import logging
import os
from typing import Any, Callable, Dict, List, Optional, Sequence

from ..errors import BusUnavailable
from ..tables.axes import AxisConfig, BusConfig, ConfigError
from . import ethercat_pdo as pdo
from .ethercat_csp import CycleSender, EthercatSetpoints
from epos_link.cia402 import State

from ..cia402_words import decode_state
from . import ethercat_slaves as slaves_info
from .ethercat_cycle import INIT, OP, SAFEOP, CycleLoop, state_name
from .ethercat_hold import (CONTROLWORD, FOLLOWS, STATUSWORD, TARGET_VELOCITY, ControlwordHold,
                             hold_command)
from .ethercat_node import EthercatNode, LinkDown, SlaveUnreachable

log = logging.getLogger("tcp_bridge.backends.ethercat")
OPTIONS = {"interface": None, "cycle_ms": 4, "watchdog_ms": 100, "sdo_timeout": 0.3,
           "op_timeout": 3.0}
CAP_HINT = ("raw Ethernet needs root or CAP_NET_RAW: sudo setcap cap_net_raw,cap_net_admin+ep "
            "on the Python interpreter (docs/hardware.md, \"EtherCAT\")")


# Set-points that start at 0, not at the drive's (a dead master's) value: target
# torque 6071h, position/velocity/torque offsets 60B0h..60B2h (CiA 402-2).
ZERO_AT_START = frozenset({0x6071, 0x60B0, 0x60B1, 0x60B2})


def _map_error(exc: BaseException) -> str:
    """One pysoem error of a ConfigMapError's list, in words."""
    where = f"slave {getattr(exc, 'slave_pos', '?')}"
    code = getattr(exc, "abort_code", None)
    if code is not None:
        return (f"{where}: SDO abort 0x{int(code):08X} at 0x{int(getattr(exc, 'index', 0)):04X}"
                f"/{int(getattr(exc, 'subindex', 0))}")
    try:
        desc = str(getattr(exc, "desc", "") or "")
    except Exception:  # pysoem's PacketError.desc raises for codes it has no text for
        desc = ""
    return f"{where}: {type(exc).__name__} {getattr(exc, 'error_code', '')} {desc}".rstrip()


def _why(exc: BaseException) -> str:
    """A pysoem error in words; its text alone can be empty (a WkcError printed as '')."""
    wkc = getattr(exc, "wkc", None)
    return (type(exc).__name__ + (f": {exc}" if str(exc) else "")
            + (f" (working counter {wkc})" if wkc is not None else ""))


# SOEM waits EC_TIMEOUTRET (2 ms) for each frame of a mailbox exchange or a state read.
# CoE transfers now run beside the cycle (ethercat_cycle rule 1), so their frames share the
# wire and the slaves with the process data; on a loaded host, or slaves that answer from
# software (the simulator, on a veth pair), 2 ms is too short and a transfer fails with
# "no answer" or a late reply to the next one ("unexpected frame"). 10 ms costs nothing
# when frames come back, and a lost frame of a state check delays one cycle by it, far
# below the slaves' watchdog. (pysoem.settings.timeouts, process-wide.)
FRAME_TIMEOUT_US = 10_000


def _frame_timeout(soem: Any) -> None:
    timeouts = getattr(getattr(soem, "settings", None), "timeouts", None)
    if timeouts is not None and int(timeouts.ret) < FRAME_TIMEOUT_US:
        timeouts.ret = FRAME_TIMEOUT_US


def _number(bus: str, key: str, value: Any, low: float, high: float) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not low <= value <= high:
        raise ConfigError(f"bus {bus}: {key} must be a number {low:g}..{high:g}, not {value!r}")
    return float(value)


def parse_options(bus: BusConfig) -> Dict[str, Any]:
    """The bus's options checked, defaults filled in; ConfigError names the key."""
    unknown = sorted(set(bus.options) - set(OPTIONS) - {"backend"})
    if unknown:
        raise ConfigError(f"bus {bus.name}: unknown ethercat options {unknown}; known: "
                          f"{', '.join(OPTIONS)}")
    opts = {**OPTIONS, **bus.options}
    if not isinstance(opts["interface"], str) or not opts["interface"]:
        raise ConfigError(f"bus {bus.name}: the ethercat backend needs interface = \"eth1\" "
                          "(the network card of the slaves)")
    opts["cycle_ms"] = _number(bus.name, "cycle_ms", opts["cycle_ms"], 1, 100)
    opts["watchdog_ms"] = _number(bus.name, "watchdog_ms", opts["watchdog_ms"], 1, 6000)
    opts["sdo_timeout"] = _number(bus.name, "sdo_timeout", opts["sdo_timeout"], 0.001, 60)
    opts["op_timeout"] = _number(bus.name, "op_timeout", opts["op_timeout"], 0.01, 60)
    if opts["watchdog_ms"] < 3 * opts["cycle_ms"]:
        raise ConfigError(f"bus {bus.name}: watchdog_ms ({opts['watchdog_ms']:g}) must be at "
                          f"least 3 cycles ({3 * opts['cycle_ms']:g} ms)")
    return opts


def _open_reason(interface: str) -> str:
    """Why a raw socket on ``interface`` could not be opened, as far as Linux tells."""
    if os.path.isdir("/sys/class/net") and not os.path.exists(f"/sys/class/net/{interface}"):
        return f"no network interface {interface} (ip link)"
    if hasattr(os, "geteuid") and os.geteuid() != 0:
        return CAP_HINT
    return "pysoem could not open it (is it up? ip link set dev IFACE up)"


def _pysoem() -> Any:
    try:
        import pysoem
    except ImportError:
        raise ConfigError("the ethercat backend needs pysoem: pip install "
                          "'epos-link[ethercat]'") from None
    return pysoem


class EthercatBackend:
    """One SOEM master on one network card; nodes by slave position."""

    # ``tcp-bridge check`` opens it read_only: slaves found and left in PREOP, where CoE
    # SDO works; no process data, no OP, so nothing is written to the drives.
    READ_ONLY_OPEN = True

    def __init__(self, bus: BusConfig, axes: Sequence[AxisConfig] = (), *,
                 soem: Optional[Any] = None, read_only: bool = False) -> None:
        self.name = bus.name
        self.read_only = read_only
        opts = parse_options(bus)
        self.interface: str = opts["interface"]
        self.soem = soem if soem is not None else _pysoem()
        self.sdo_timeout: float = opts["sdo_timeout"]
        _frame_timeout(self.soem)
        master = self.soem.Master()
        try:
            master.open(self.interface)
        except (ConnectionError, OSError) as exc:
            raise BusUnavailable(f"bus {bus.name}: cannot open {self.interface}: "
                                 f"{_open_reason(self.interface)} ({exc})") from None
        self.cyclic: Optional[CycleSender] = None
        try:
            self.cycle = self._configure(master, opts)
        except BaseException:
            master.close()
            raise
        self.nodes: Dict[int, EthercatNode] = {}
        # Internal axes in CSP (issue 26): set-points made on the cycle itself (.ethercat_csp).
        self.cyclic_nodes = frozenset(a.node_id for a in axes if a.cyclic is not None)
        if self.cyclic_nodes and not read_only:
            self.cyclic = CycleSender(bus.name, EthercatSetpoints(self), self.cycle.period,
                                      self.cycle.add_hook, self.cycle.remove_hook)
            self.cyclic.begin()
        missing = [a.node_id for a in axes if a.node_id not in self.cycle.slaves]
        if missing:
            log.warning("bus %s: no slave at position %s (%d found): those axes are absent",
                        self.name, ", ".join(map(str, missing)), len(self.cycle.slaves))

    def _configure(self, master: Any, opts: Dict[str, Any]) -> CycleLoop:
        found = int(master.config_init())
        if found < 1:
            raise BusUnavailable(f"bus {self.name}: no EtherCAT slave answers on {self.interface} "
                                 "(cable, the slaves' power)")
        master.sdo_read_timeout = master.sdo_write_timeout = int(self.sdo_timeout * 1e6)
        slaves = {p: s for p, s in enumerate(master.slaves, start=1)}
        for position, slave in slaves.items():
            log.info("bus %s: slave %d %s vendor 0x%08X product 0x%08X revision 0x%08X",
                     self.name, position, slave.name, slave.man, slave.id, slave.rev)
        self.layouts: Dict[int, Optional[pdo.Layout]] = {}
        self.notes: Dict[int, List[str]] = {}  # per slave, for inventory() (tcp-bridge check)
        self.hold: Optional[ControlwordHold] = None
        if self.read_only:  # every object by SDO, in PREOP
            master.read_state()
            for position, slave in slaves.items():
                self._probe_ca(position, slave)
                self._probe_objects(position, slave)
            loop = CycleLoop(master, {}, opts["cycle_ms"] / 1000.0,
                             al_text=self.soem.al_status_code_to_string)
            loop.slaves = slaves
            return loop
        slaves = self._map(master, slaves)  # the slaves are in SAFEOP now
        for position, slave in slaves.items():
            try:
                slave.set_watchdog("processdata", float(opts["watchdog_ms"]))
            except Exception as exc:  # pysoem marks it experimental: the default (100 ms) stays
                log.warning("bus %s: slave %d: watchdog not set: %s", self.name, position, exc)
            self._probe_objects(position, slave)
        cycle = CycleLoop(master, slaves, opts["cycle_ms"] / 1000.0,
                          al_text=self.soem.al_status_code_to_string,
                          silent_after=opts["watchdog_ms"] / 1000.0)
        for position, layout in self.layouts.items():
            if layout is not None:
                self._seed(slaves[position], position, cycle.outputs[position], layout)
        self.hold = ControlwordHold(cycle, self.layouts)  # ethercat_hold: the drive decides
        cycle.input_hooks.append(self.hold.check)
        cycle.on_lost = self._lost
        cycle.start()
        try:
            # Outputs that follow each drive, made from inputs of cycles in SAFE-OP, before OP.
            cycle.wait_cycles(3, max(1.0, 50 * cycle.period))
            self._to_op(master, cycle, opts["op_timeout"])
        except BaseException:
            cycle.stop()
            raise
        return cycle

    # -- configuration: Complete Access, layouts, objects (ethercat_slaves) -------------

    def _map(self, master: Any, slaves: Dict[int, Any]) -> Dict[int, Any]:
        """config_map(); once more without Complete Access if that fails (module doc)."""
        why = self._try_map(master, slaves)
        if why is None:
            return slaves
        log.warning("bus %s: configuring the slaves failed (%s): configuring them again "
                    "without SDO Complete Access", self.name, why)
        master.config_init()
        slaves = {p: s for p, s in enumerate(master.slaves, start=1)}
        for position, slave in slaves.items():
            disable = getattr(slave, "_disable_complete_access", None)
            if callable(disable):
                disable()
            self.notes.setdefault(position, []).append(
                f"configured without SDO Complete Access ({why})")
        why = self._try_map(master, slaves)
        if why is not None:
            log.warning("bus %s: without Complete Access too: %s", self.name, why)
        else:
            log.warning("bus %s: configured without Complete Access", self.name)
        return slaves

    def _try_map(self, master: Any, slaves: Dict[int, Any]) -> Optional[str]:
        """None when the I/O map is right; else why not. Fills :attr:`layouts`."""
        try:
            master.config_map()
        except self.soem.ConfigMapError as exc:
            errors = getattr(exc, "error_list", None) or [exc]
            return "config_map: " + "; ".join(_map_error(e) for e in errors)
        if master.state_check(SAFEOP, 2_000_000) != SAFEOP:
            master.read_state()
            late = [p for p, s in slaves.items() if int(s.state) & 0x0F != SAFEOP]
            if late:
                return "; ".join(self._describe_state(p, slaves[p]) for p in late)
        problems = []
        for position, slave in slaves.items():
            layout, problem = self._layout(position, slave)
            self.layouts[position] = layout
            if problem:
                problems.append(f"slave {position}: {problem}")
        return "; ".join(problems) or None

    def _setup_read(self, position: int, slave: Any, index: int, subindex: int) -> bytes:
        """A CoE read of the set-up, made once more when its frames got no answer, as
        every transfer of a running bus is (EthercatNode._twice): a frame lost on a loaded
        host is not a slave without a PDO mapping, and a mapping left unread puts every
        object of the slave on SDO for the bridge's life. (Under load a suite saw
        'slave 2: PDO mapping unreadable (): every object by SDO', then 2S04=1 NAK.)"""
        try:
            return bytes(slave.sdo_read(index, subindex, ca=False))
        except self.soem.WkcError as exc:
            log.info("bus %s: slave %d: a CoE read of 0x%04X/%d at set-up got no answer "
                     "(working counter %s): made once more", self.name, position, index,
                     subindex, getattr(exc, "wkc", "?"))
        return bytes(slave.sdo_read(index, subindex, ca=False))

    def _describe_state(self, position: int, slave: Any) -> str:
        code = int(getattr(slave, "al_status", 0) or 0)
        return (f"slave {position} is in {state_name(int(slave.state))}"
                + (f", AL status 0x{code:04X} {self.soem.al_status_code_to_string(code)}"
                   if code else ""))

    def _layout(self, position: int, slave: Any) -> "tuple[Optional[pdo.Layout], str]":
        try:
            layout = pdo.read_layout(lambda i, s: self._setup_read(position, slave, i, s))
        except Exception as exc:
            log.warning("bus %s: slave %d: PDO mapping unreadable (%s): every object by SDO",
                        self.name, position, _why(exc))
            return None, ""
        problem = pdo.layout_problem(layout, len(bytes(slave.output)), len(bytes(slave.input)))
        if problem:
            log.warning("bus %s: slave %d: %s: every object by SDO", self.name, position, problem)
            return None, problem
        return layout, ""

    def _abort_code(self, exc: BaseException) -> Optional[int]:
        if isinstance(exc, self.soem.SdoError):
            return int(getattr(exc, "abort_code", 0))
        return None

    def _probe_objects(self, position: int, slave: Any) -> None:
        """One line per object the slave lacks (ethercat_slaves): logged, and kept for check."""
        missing = slaves_info.missing_objects(lambda i, s: slave.sdo_read(i, s, ca=False),
                                              self._abort_code)
        for key, mandatory, what in missing:
            line = slaves_info.missing_line(position, key, mandatory, what)
            (log.warning if mandatory else log.info)("bus %s: %s", self.name, line)
            self.notes.setdefault(position, []).append(line.split(": ", 1)[1])

    def _probe_ca(self, position: int, slave: Any) -> None:
        """check (read only, no config_map): would SOEM misread this slave's CA answers?"""
        try:
            details = slaves_info.sii_coe_details(
                lambda word: int.from_bytes(bytes(slave.eeprom_read(word))[:2], "little"))
        except Exception:
            details = None
        if details is not None and not details & slaves_info.COE_DETAILS_CA:
            return  # not offered: SOEM reads object by object
        for index in (0x1C12, 0x1C13):
            try:
                expected = slaves_info.expected_ca(lambda i, s: slave.sdo_read(i, s, ca=False),
                                                   index)
                answer = bytes(slave.sdo_read(index, 0, ca=True))
                problem = slaves_info.ca_problem(answer, expected)
            except Exception as exc:
                code = self._abort_code(exc)
                problem = (f"it refuses Complete Access (SDO abort 0x{code:08X})"
                           if code is not None else f"its Complete Access answer failed ({exc})")
            if problem:
                self.notes.setdefault(position, []).append(
                    f"{problem} ({index:04X}h): serve configures it without Complete Access")
                return

    def _seed(self, slave: Any, position: int, image: bytearray, layout: pdo.Layout) -> None:
        """The outputs before the first cycle. Those the hold makes follow the drive
        (:mod:`.ethercat_hold`, from the inputs) are left to it; the others start as what
        the drive shows now, by SDO: the controlword of a slave without 6041h in its
        inputs is the hold of the state read now, 607Ah is 6064h, 6060h is 6061h;
        60FFh, torque and offsets are 0; any other object is the drive's own value."""
        read = lambda key: bytes(slave.sdo_read(key[0], key[1], ca=False))  # noqa: E731
        for key, entry in layout.outputs.items():
            if key == TARGET_VELOCITY or entry.index in ZERO_AT_START:
                continue  # the image starts as zeros
            source = FOLLOWS.get(key, key)
            if key in FOLLOWS and source in layout.inputs:
                continue  # the hold follows it from the first cycle's inputs
            try:
                if key == CONTROLWORD:
                    held = hold_command(decode_state(int.from_bytes(read(STATUSWORD)[:2],
                                                                    "little")))
                    data = held.to_bytes(entry.size, "little")
                    log.warning("bus %s: slave %d maps no statusword 6041h in its inputs: its "
                                "controlword starts as 0x%04X (its state read now) and cannot "
                                "follow its drive later", self.name, position, held)
                else:
                    try:
                        data = read(source)
                    except Exception:
                        data = read(key)  # no 6061h/6064h by SDO either: its own value
                pdo.put(image, entry, data[:entry.size].ljust(entry.size, b"\0"))
            except Exception:
                if key == CONTROLWORD:  # no state known: disable voltage, never up
                    held = hold_command(State.NOT_READY_TO_SWITCH_ON)
                    pdo.put(image, entry, held.to_bytes(entry.size, "little"))

    def _lost(self, position: int, why: str) -> None:
        """The cycle found ``position`` out of OP (cycle thread, under its lock)."""
        # The cyclic sender sees the slave lost in its next cycle (cycle.lost) and ramps the
        # rest of its line down (motion/cyclic.py, "a line is one motion"); ending the runs
        # here would stop the other axes dead at their last set-point instead.
        if self.hold is not None:
            self.hold.follow(position, f"dropped out: {why}")

    def _to_op(self, master: Any, cycle: CycleLoop, timeout: float) -> None:
        try:
            self._request_op(master, cycle, timeout)
        finally:
            cycle.supervise = True

    def _request_op(self, master: Any, cycle: CycleLoop, timeout: float) -> None:
        with cycle.lock:
            master.state = OP
            master.write_state()
        attempts = max(1, int(timeout / 0.05))
        for _ in range(attempts):
            with cycle.lock:
                if master.state_check(OP, 1000) == OP:
                    return
            cycle.wait_cycles(1, 0.05)
        with cycle.lock:
            master.read_state()
            for position in cycle.slaves:
                if int(cycle.slaves[position].state) != OP and position not in cycle.lost:
                    cycle.lost[position] = cycle.describe(position)
                    log.warning("bus %s: %s: its axis is silent until it reaches OP",
                                self.name, cycle.lost[position])
            cycle._check = True  # the recovery asks again

    # -- the Backend interface ----------------------------------------------------------

    def node(self, node_id: int) -> EthercatNode:
        node = self.nodes.get(node_id)
        if node is None:
            node = self.nodes[node_id] = EthercatNode(self, node_id)
            if node_id in self.cyclic_nodes:
                node.cyclic = self.cyclic
        return node

    def add_cycle_hook(self, hook: Callable[[int], None]) -> None:
        """``hook(cycle_number)`` at the start of every cycle (:class:`CycleLoop`)."""
        self.cycle.add_hook(hook)

    def remove_cycle_hook(self, hook: Callable[[int], None]) -> None:
        self.cycle.remove_hook(hook)

    @property
    def cycle_s(self) -> float:
        return self.cycle.period

    def inventory(self) -> List[str]:
        """One line per slave found: position, name, identity, state; then one line per
        thing it lacks (Complete Access, objects: :mod:`.ethercat_slaves`)."""
        lines = []
        for position, slave in self.cycle.slaves.items():
            lines.append(f"slave {position}: {slave.name} vendor 0x{int(slave.man):08X} product "
                         f"0x{int(slave.id):08X} revision 0x{int(slave.rev):08X} "
                         f"{state_name(int(slave.state))}")
            lines.extend(f"slave {position}: {note}" for note in self.notes.get(position, ()))
        return lines

    def probe(self) -> None:
        """Does any frame come back? (:mod:`tcp_bridge.bus.failfast`.)"""
        if self.cycle.link_down:
            raise LinkDown(f"no EtherCAT frame comes back on {self.interface}")

    def describe_silence(self, why: str) -> str:
        return (f"the EtherCAT slaves on {self.interface} do not answer ({why}): check the "
                "cable from the card to the first slave and the slaves' power")

    def close(self) -> None:
        if self.cyclic is not None:  # cyclic moves ramp down while the cycle goes on
            self.cyclic.finish_runs()
            self.cyclic.kill()
        self.cycle.stop()
        with self.cycle.lock:
            try:
                self.cycle.master.state = INIT  # the drives see the master leave
                self.cycle.master.write_state()
            except Exception:
                pass
            self.cycle.master.close()


__all__ = ["EthercatBackend", "EthercatNode", "LinkDown", "SlaveUnreachable", "parse_options"]
