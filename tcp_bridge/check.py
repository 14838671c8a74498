"""``tcp-bridge check``: a read-only pre-flight of the axis table against the drives.

::

    tcp-bridge check --config axes.toml [--json] [-v]
    tcp-bridge check --simulate [--axes N] [--json]

It opens every bus of the table with the bridge's own backends
(:mod:`tcp_bridge.backends`) and, for each axis with a node, *reads* the
device type (0x1000), name (0x1008), identity (0x1018/01..04), statusword
(6041h), mode display (6061h) and actual position (6064h), and for a maxon
EPOS4 (device 5) its velocity unit (60A9h) and main sensor resolution
(3000h/05h). :mod:`tcp_bridge.preflight` turns that into one verdict per axis.
Exit status 0 when every axis answers as configured, 1 otherwise, 2 when the
table itself cannot be used.

**It writes nothing to any drive**: only SDO uploads (``node.sdo.upload``),
no download, no NMT command, no PDO (tests count the writes at the simulated
drives' object stores). Opening a backend sends nothing either: a python-can
bus, an ``EposClient`` on a serial/USB link, or the embedded simulator. The
state file is read (so that inversion and offset of S22/S25 apply to the
position shown) and never written.

The link before the nodes: a backend with a ``probe()`` (``epos``, ``sim``:
a read of the EPOS4's own device type as node 0) is probed first, up to
:data:`PROBE_ATTEMPTS` times. When its device gives no answer at all, every
axis of the bus is "device silent", with one line naming the device's URL and
what to check (port, baud rate, power), and its nodes are not asked: a node is
called absent only when the device in front of it answers.

After the table, a bus that finds its devices itself (``ethercat``) lists each
slave by position (the axis's ``node_id``) with its identity from the SII and its
EtherCAT state; then one line per bus says what stops its axes if the host (the
bridge) dies (:func:`liveness_notes`; docs/hardware.md, "When the host dies"):
the drives' heartbeat consumer on a ``canopen`` bus with ``heartbeat_ms``;
nothing from the host otherwise, nor through an EPOS4 gateway, which forwards
SDO only. With ``--json`` these lines go to stderr. The check itself sends no
heartbeat: it opens buses, the engine is what starts the heartbeat.

Time: a silent device costs its probes (each waits as long as one of ``serve``'s
requests, the bus's ``timeout``, 0.5 s by default: a device that serve serves is
never called silent here); an absent node costs one SDO timeout
(its first read), then the check moves on; one that answers costs a dozen
uploads. Buses are checked one after the other, each closed before the next opens.
"""
from __future__ import annotations

import argparse
import logging
import sys
from typing import Any, Callable, Dict, List, Optional, Tuple

from .tables.axes import AxisConfig, AxisTable, BusConfig, ConfigError, DeviceCode, simulated_table
from .errors import BridgeError, DeviceFailure
from .tables.parameters import ParameterStore
from .preflight import AxisReport, Reading, as_json, device_silent, judge, no_bus, no_drive
from .preflight import table as format_table
from .bus.health import Silence
from .bus.sdo import NodeSilent, SdoPort, silence_of

Opener = Callable[[BusConfig, List[AxisConfig]], Any]

# (key in Reading.failures, attribute, index, subindex); read in this order.
IDENTITY = (("1018h/01", "vendor_id", 0x1018, 1), ("1018h/02", "product_code", 0x1018, 2),
            ("1018h/03", "revision", 0x1018, 3), ("1018h/04", "serial", 0x1018, 4))
DRIVE = (("6041h", "statusword", 0x6041, 0), ("6061h", "mode", 0x6061, 0),
         ("6064h", "position", 0x6064, 0))
EPOS4_UNITS = (("60A9h", "velocity_unit", 0x60A9, 0), ("3000h/05", "sensor_resolution", 0x3000, 5))
PROBE_ATTEMPTS = 3  # a lost exchange (a port just opened) is not a silent device


def read_node(port: SdoPort, device: DeviceCode) -> Reading:
    """Upload the objects of the check from one node; never a download.

    The first read (0x1000, mandatory for every CANopen device) tells whether
    the node is there at all; a silent node is not asked anything else.
    """
    reading = Reading()
    try:
        reading.device_type = port.read(0x1000, 0, size=4, signed=False)
    except NodeSilent as exc:
        reading.silent = _why(exc)
        return reading
    except DeviceFailure as exc:
        reading.failures["1000h"] = _why(exc)
    _describe_device_name(port.node)
    try:
        reading.name = port.upload(0x1008, 0).rstrip(b"\0").decode("latin-1")
    except DeviceFailure as exc:
        reading.failures["1008h"] = _why(exc)
    objects: Tuple[Tuple[str, str, int, int], ...] = IDENTITY + DRIVE
    if device is DeviceCode.C_DC_MAXON_EPOS4:
        objects += EPOS4_UNITS
    for key, attribute, index, subindex in objects:
        try:
            setattr(reading, attribute, port.read(index, subindex))
        except DeviceFailure as exc:
            reading.failures[key] = _why(exc)
    return reading


def _describe_device_name(node: Any) -> None:
    """Tell the node's dictionary that 0x1008 is a VISIBLE_STRING (CiA 301 object 1008h).

    The epos_link gateway adapter reads an object its dictionary does not
    describe with ReadObject, 4 bytes ("EPOS" of "EPOS4"); described as a
    string it is read whole (segmented). The epos and sim backends default to
    an empty dictionary. This changes only the check's own node object.
    """
    from canopen.objectdictionary import ObjectDictionary, ODVariable, datatypes

    od = getattr(getattr(node, "sdo", None), "od", None)
    if isinstance(od, ObjectDictionary) and 0x1008 not in od:
        name = ODVariable("Manufacturer device name", 0x1008, 0)
        name.data_type = datatypes.VISIBLE_STRING
        od.add_object(name)


def _why(exc: DeviceFailure) -> str:
    """The device's answer without the port's name and object (the row already says them)."""
    return str(exc).split(" failed: ", 1)[-1]


def check(axis_table: AxisTable, *, opener: Optional[Opener] = None,
          found: Optional[List[str]] = None) -> List[AxisReport]:
    """One report per axis of ``axis_table``, in AxAddr order. Reads only (module docstring).

    ``found`` receives one line per device a bus discovered by itself (an ``ethercat``
    bus: each slave by position with its identity), for the lines after the table."""
    if opener is None:
        opener = _open_read_only
    params = ParameterStore(axis_table, read_only=True)  # the state file's inversion/offset
    reports: Dict[int, AxisReport] = {}
    try:
        for name, bus in axis_table.buses.items():
            axes = [a for a in axis_table.axes.values() if a.bus == name and a.has_node]
            if axes:
                reports.update(_check_bus(bus, axes, params, opener, found))
        for addr, axis in axis_table.axes.items():
            if not axis.has_node:
                reports[addr] = no_drive(axis)
    finally:
        params.close()
    return [reports[addr] for addr in sorted(reports)]


GATEWAY_NOTE = ("through the EPOS4 gateway the host's liveness cannot reach the CAN bus: the "
                "gateway forwards SDO only (Communication Guide chapter 5), and the guide names "
                "no watchdog of the USB/RS232 host (2005h/2006h end an incomplete frame, 2.2.7); "
                "if the bridge dies, the drives keep their last command.\n"
                "  What protects the axes then: the drives' own limits (software position limits "
                "607Dh, max profile velocity 607Fh, max following error 6065h) and a hardware "
                "STO / emergency stop circuit (docs/hardware.md, \"When the host dies\")")


def liveness_notes(axis_table: AxisTable) -> List[str]:
    """One line per bus with axes: what stops them if the bridge's process dies."""
    from .backends.heartbeat import heartbeat_settings

    notes = []
    for name, bus in axis_table.buses.items():
        axes = [a for a in axis_table.axes.values() if a.bus == name and a.has_node]
        if not axes:
            continue
        can = bus.backend == "canopen" or (bus.backend == "sim" and bus.options.get("link") == "can")
        if bus.backend in ("epos", "sim") and not can:
            notes.append(f"bus {name}: {GATEWAY_NOTE}")
            continue
        if not can:
            continue  # instant and plug-in backends: nothing known to say
        try:
            hb = heartbeat_settings(name, dict(bus.options), axes)
        except ConfigError:
            continue  # the bus's row already says why it cannot be used
        if hb is None:
            notes.append(f"bus {name}: no heartbeat (heartbeat_ms unset): if the bridge dies, "
                         "the drives keep their last command; set heartbeat_ms to have them stop")
        else:
            reaction = {3: "quick stop", 2: "disable voltage", 1: "fault"}[hb.abort_connection]
            notes.append(f"bus {name}: the bridge's heartbeat (node {hb.producer_id}, every "
                         f"{hb.period_ms} ms) is watched by each drive it enables: if the bridge "
                         f"dies, a drive reacts ({reaction}, 6007h) after {hb.consumer_ms} ms "
                         "without it and sends EMCY 8130h")
    return notes


_REACTIONS = {0: "no action", 1: "fault", 2: "disable voltage", 3: "quick stop"}


def read_supervision(port: SdoPort, bus: BusConfig, axes: List[AxisConfig],
                     statusword: Optional[int]) -> str:
    """What stops this drive if the bridge dies, as read from the drive itself (issue 30
    finding 4): its heartbeat consumer 1016h:01 (CiA 301 7.5.2.19: producer node-ID
    in bits 23..16, time in ms in 15..0) and its reaction 6007h (CiA 402-2); on
    EtherCAT only 6007h, the reaction to the SM watchdog, whose registers no CoE read
    reaches. Reads only; a drive in OPERATION ENABLED or QUICK STOP ACTIVE with no
    consumer is UNSUPERVISED."""
    from epos_link.cia402 import State, state_from_statusword

    from .backends.heartbeat import heartbeat_settings

    def read(index: int, sub: int, size: int, signed: bool) -> Optional[int]:
        try:
            return port.read(index, sub, size=size, signed=signed)
        except DeviceFailure:
            return None

    reaction = read(0x6007, 0, 2, True)
    said = ("6007h unreadable" if reaction is None
            else f"6007h = {reaction} ({_REACTIONS.get(reaction, 'manufacturer specific')})")
    if bus.backend == "ethercat":
        return (f"SM watchdog of the process data (watchdog_ms, set when the bridge serves); "
                f"its reaction {said}")
    state = state_from_statusword(statusword) if statusword is not None else None
    moving = state in (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE)
    entry = read(0x1016, 1, 4, False)
    if entry is None:
        return f"1016h:01 unreadable, {said}" + (": UNSUPERVISED while enabled" if moving else "")
    node, ms = (entry >> 16) & 0xFF, entry & 0xFFFF
    if node == 0 or ms == 0:
        if moving and state is not None:
            return (f"UNSUPERVISED: no heartbeat consumer (1016h:01 = 0) while {state.name}: "
                    "if the bridge dies, it keeps its last command")
        return "no heartbeat consumer (1016h:01 = 0)"
    text = f"heartbeat consumer of node {node}, {ms} ms (1016h:01); {said}"
    try:
        hb = heartbeat_settings(bus.name, dict(bus.options), axes)
    except ConfigError:
        hb = None
    if hb is not None and node != hb.producer_id:
        text += f"; not the bridge's heartbeat (node {hb.producer_id})"
    return text


def _open_read_only(bus: BusConfig, axes: List[AxisConfig]) -> Any:
    """The bus's backend, opened read-only if its factory offers that (``ethercat``:
    slaves left in PREOP, no process data: nothing written to the drives)."""
    from .backends import factory_for

    factory = factory_for(bus.backend)
    if getattr(factory, "READ_ONLY_OPEN", False):
        return factory(bus, list(axes), read_only=True)
    return factory(bus, list(axes))


def _check_bus(bus: BusConfig, axes: List[AxisConfig], params: ParameterStore,
               opener: Opener, found: Optional[List[str]] = None) -> Dict[int, AxisReport]:
    try:
        backend = opener(bus, axes)
    except (ConfigError, OSError) as exc:
        return {a.addr: no_bus(a, str(exc)) for a in axes}
    try:
        inventory = getattr(backend, "inventory", None)
        if callable(inventory) and found is not None:
            found.extend(f"bus {bus.name}: {line}" for line in inventory())
        silent = _device_silence(bus, backend)
        if silent is not None:
            return {a.addr: device_silent(a, silent) for a in axes}
        out: Dict[int, AxisReport] = {}
        for axis in axes:
            port = SdoPort(backend.node(axis.node_id), name=f"axis {axis.addr}")
            reading = read_node(port, axis.device)
            if reading.silent is None:
                reading.supervision = read_supervision(port, bus, axes, reading.statusword)
            out[axis.addr] = judge(axis, reading, params.scaling(axis.addr))
        return out
    finally:
        backend.close()


def _device_silence(bus: BusConfig, backend: Any) -> Optional[str]:
    """Why the bus's own device is silent (one line naming it), or None if it answers
    or the backend has no ``probe()`` (a CAN adapter: its nodes are asked directly)."""
    # The wait of serve's requests, where the backend has it: what serve serves is never
    # "device silent" here (EposBackend.patient_probe).
    probe = getattr(backend, "patient_probe", None) or getattr(backend, "probe", None)
    if not callable(probe):
        return None
    why = ""
    for _ in range(PROBE_ATTEMPTS):
        try:
            probe()
            return None
        except Exception as exc:
            if silence_of(exc) is not Silence.LINK:
                return None  # an abort is an answer: the device is there
            why = str(exc)
    describe = getattr(backend, "describe_silence", None)
    if callable(describe):
        return f"bus {bus.name}: {describe(why)}"
    return f"bus {bus.name}: its device does not answer ({why})"


# -- command line (wired into tcp_bridge.cli) ------------------------------------------------


def add_arguments(p: argparse.ArgumentParser) -> None:
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--config", metavar="FILE", help="axis table (TOML) to check")
    src.add_argument("--simulate", action="store_true",
                     help="check the simulated drives that serve --simulate would use")
    p.add_argument("--axes", type=_axes, default=3, metavar="N",
                   help="with --simulate: how many simulated axes (default 3)")
    p.add_argument("--json", action="store_true",
                   help="one JSON object per axis (addr, verdict, ok, detail, what was read)")
    p.add_argument("-v", "--verbose", action="store_true",
                   help="log the backends' own messages (canopen, python-can)")


def _axes(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of axes") from None


def run(args: argparse.Namespace, prog: str = "tcp-bridge check") -> int:
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(name)s: %(message)s")
    if not args.verbose:
        # An absent node's SDO timeout is the check's answer "absent", not a log line.
        logging.getLogger("canopen").setLevel(logging.CRITICAL)
    try:
        axes = simulated_table(args.axes) if args.simulate else AxisTable.load(args.config)
        found: List[str] = []
        reports = check(axes, found=found)
    except (ConfigError, BridgeError) as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        return 2
    if args.json:
        for report in reports:
            print(as_json(report))
    else:
        print(format_table(reports))
    supervision = [f"axis {r.axis.addr} supervision: {r.reading.supervision}"
                   for r in reports if r.reading.supervision is not None]
    for note in [*found, *liveness_notes(axes), *supervision]:
        print(note, file=sys.stderr if args.json else sys.stdout)
    return 0 if all(r.ok for r in reports) else 1

