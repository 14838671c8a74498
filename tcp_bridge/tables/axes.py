"""The axis table of the gateway (spec section 3) and its parameter array.

Spec 3: "the axis settings and the axis parameters are stored in an array. For
each axis there is an array and the system supports up to 60 axes." An axis is
``AxAddr`` (3.1), a device code (3.5), the internal flag (3.2), a bus offset
(3.3), a node id (3.4) and the position user-unit factor (3.6). The parameters
are the internal parameters of the command table (spec 4), kept here by TCP
command number (2, 5, 6, 19..63, 80) in their stored form: an integer, and for
the ``*`` ones ``round(user value * factor)`` (spec 4 footnote).

The table is read from a TOML file by :mod:`tcp_bridge.tables.config` (every
mistake is one line naming the file, the table and the key);
``tcp_bridge/example_axes.toml`` documents every key. :func:`_validate` holds
the rules between axes, for tables built in code too; a table without axes
is refused. Parameters changed with S commands are kept in a JSON state file,
written atomically (temporary file, fsync, rename) after every change and
overlaid on the TOML values at start, as the controller keeps them in its
arrays across restarts.

Device codes: spec 3.5 defines 0..4. This bridge adds
``C_DC_MAXON_EPOS4 = 5`` for the maxon EPOS4 (a plain CiA 402 drive: position
read from 6064h, detailed error from 603Fh, see :mod:`tcp_bridge.engine`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import IntEnum
from pathlib import Path
from types import MappingProxyType
from typing import Any, Dict, Final, Mapping, Optional, Tuple, Union

from .commands import COMMANDS, CommandKind, CommandSpec
from ..errors import ConfigError
from ..wire import MAX_AXIS
from .units import Number, Scaling, stored_parameter


class DeviceCode(IntEnum):
    """Spec 3.5 device codes; 5 is this bridge's addition for the maxon EPOS4."""

    C_DC_NOT_DEFINED = 0
    C_DC_NANOTEC = 1
    C_DC_TECHNOSOFT_CAN = 2
    C_DC_TECHNOSOFT_EC = 3
    C_DC_COBLEY_CAN = 4  # sic, the spec's spelling of Copley
    C_DC_MAXON_EPOS4 = 5


# Short names accepted in the TOML file besides the numbers.
DEVICE_NAMES: Final = {
    "not_defined": DeviceCode.C_DC_NOT_DEFINED, "nanotec": DeviceCode.C_DC_NANOTEC,
    "technosoft_can": DeviceCode.C_DC_TECHNOSOFT_CAN,
    "technosoft_ec": DeviceCode.C_DC_TECHNOSOFT_EC, "copley_can": DeviceCode.C_DC_COBLEY_CAN,
    "maxon_epos4": DeviceCode.C_DC_MAXON_EPOS4,
}


class BusOffset(IntEnum):
    """Spec 3.3: which bus a device is on."""

    CAN1 = 0
    CAN2 = 100_000
    ETHERCAT = 1_000_000


BUS_NAMES: Final = {BusOffset.CAN1: "can1", BusOffset.CAN2: "can2", BusOffset.ETHERCAT: "ethercat"}

# TCP command number -> TOML name of the parameters kept in the array.
PARAMETER_NAMES: Final = MappingProxyType({
    2: "target_position", 5: "velocity", 6: "acceleration", 19: "device_code",
    20: "scale_n", 21: "scale_z", 22: "axis_inversion", 23: "limit_positive",
    24: "limit_negative", 25: "offset", 26: "max_velocity", 27: "max_acceleration",
    28: "quickstop_accel", 29: "slave_axis", 30: "slave_direction", 31: "possible_modes",
    32: "dynamic_limits", 40: "homing_mode", 41: "homing_velocity_switch",
    42: "homing_velocity_index", 43: "homing_acceleration", 53: "output_function",
    54: "output_delay", 56: "control_brake", 60: "encoder_type", 62: "following_error",
    63: "encoder_direction", 80: "sdo_index",
})
PARAMETER_NUMBERS: Final = MappingProxyType({v: k for k, v in PARAMETER_NAMES.items()})
assert set(PARAMETER_NAMES) == {n for n, c in COMMANDS.items() if c.kind is CommandKind.PARAMETER}

# Defaults of the parameter array, in user units. None: nothing is stored, the
# drive's own value stands (reads return it, "write all parameters" skips it).
# 19 (device code) comes from the axis itself.
DEFAULTS: Final[Mapping[int, Optional[Number]]] = MappingProxyType({
    2: None, 5: None, 6: None, 20: 1, 21: 1, 22: 1, 23: None, 24: None, 25: 0.0,
    26: None, 27: None, 28: None, 29: 0, 30: 1, 31: 3, 32: 0, 40: None, 41: None,
    42: None, 43: None, 53: None, 54: 0, 56: 0, 60: 0, 62: None, 63: None,
    80: 0x60410002,  # statusword, 2 bytes: a harmless selector for 81
})

# Command 19 may name the EPOS4 code too (the command table lists 0..4 of spec 3.5).
DEVICE_CODE_SPEC: Final = CommandSpec(
    19, "Device Code", True, True, CommandKind.PARAMETER, parameter=2,
    choices=frozenset(int(c) for c in DeviceCode),
)


def parameter_spec(cmd: int) -> CommandSpec:
    """The command spec used to validate parameter ``cmd`` (19 widened to code 5)."""
    return DEVICE_CODE_SPEC if cmd == 19 else COMMANDS[cmd]


def to_stored(spec: CommandSpec, value: Number, factor: int) -> int:
    """The stored (integer) form of a user value of parameter ``spec``."""
    if spec.scaled:
        return stored_parameter(value, factor)
    return int(value)


def from_stored(spec: CommandSpec, stored: int, factor: int) -> Number:
    """The user value of a stored parameter."""
    return Scaling(factor).from_drive(stored) if spec.scaled else stored


@dataclass(frozen=True)
class BusConfig:
    """One bus (spec 3.3) and the backend that reaches it, with its options."""

    name: str
    backend: str
    options: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class AxisConfig:
    """One row of the axis table (spec 3)."""

    addr: int
    device: DeviceCode = DeviceCode.C_DC_NOT_DEFINED
    internal: bool = False
    bus_offset: BusOffset = BusOffset.CAN1
    node_id: int = 0
    position_factor: int = 1
    # Configured parameter values in user units, by command number.
    parameters: Mapping[int, Number] = field(default_factory=dict)
    # Device 5 (EPOS4): motor encoder increments per motor revolution, after
    # quadrature (4 x 3010h/01h pulses); velocities are rpm (tcp_bridge.tables.units).
    increments_per_revolution: Optional[int] = None
    # Spec 3.2 internal axis whose profile the bridge computes: "csp" (cyclic synchronous
    # position, streamed by tcp_bridge.motion.cyclic; CSV for velocity moves); None: the
    # drive's own profile modes. An axis table gives it with internal = true alone (a
    # drive: node_id set); profile = "drive" opts out (tables.config).
    cyclic: Optional[str] = None
    # The EPICS motor record's name after the prefix (tcp_bridge.epics); None: m<AxAddr>.
    epics_name: Optional[str] = None
    # R82 of a cyclic axis whose drive has no position window 6067h (optional in CiA 402-2
    # for CSP): this window, in increments; None: DEFAULT_POSITION_WINDOW.
    position_window: Optional[int] = None

    @property
    def bus(self) -> str:
        return BUS_NAMES[self.bus_offset]

    @property
    def has_node(self) -> bool:
        """An internal axis with node id 0 is the controller's own (spec 3 example)."""
        return self.node_id != 0


@dataclass(frozen=True)
class Settings:
    """Timing and behaviour of the command layer and the server (the ``[bridge]`` table)."""

    ack_timeout: float = 2.0  # bound for the ACK of 00 and 04 (drive acceptance)
    state_timeout: float = 1.0  # bound for one state machine step / mode change
    reset_timeout: float = 5.0  # bound for a node to answer again after NMT reset
    reset_delay: float = 0.3  # pause after the NMT reset before polling the node
    poll_interval: float = 0.002  # pause between statusword polls
    debug: bool = False  # initial value of command 91
    state_file: Optional[Path] = None
    # Server (tcp_bridge.server): None = the server's default (60 s, see its docstring).
    idle_timeout: Optional[float] = None
    # Client networks served (tcp_bridge.access); None = the default, loopback only.
    allow: Optional[Tuple[Any, ...]] = None
    # Fail-fast buses (tcp_bridge.bus.health): seconds between probes of a silent bus.
    probe_interval: float = 0.25

    def __post_init__(self) -> None:
        for name in ("ack_timeout", "state_timeout", "reset_timeout", "probe_interval"):
            if not _positive(getattr(self, name)):
                raise ConfigError(f"[bridge] {name} must be positive")
        for name in ("reset_delay", "poll_interval"):
            value = getattr(self, name)
            if not (_positive(value) or value == 0):
                raise ConfigError(f"[bridge] {name} must not be negative")
        if self.idle_timeout is not None and not _positive(self.idle_timeout):
            raise ConfigError("[bridge] idle_timeout must be positive")


def _positive(value: Any) -> bool:
    return (isinstance(value, (int, float)) and not isinstance(value, bool)
            and math.isfinite(value) and value > 0)


@dataclass(frozen=True)
class AxisTable:
    """Axes by AxAddr, buses by name, settings."""

    axes: Mapping[int, AxisConfig]
    buses: Mapping[str, BusConfig]
    settings: Settings = Settings()
    source: str = field(default="axis table", compare=False)  # file name, for messages
    epics_prefix: Optional[str] = None  # [epics] prefix: serve motor records (tcp_bridge.epics)

    def __post_init__(self) -> None:
        _validate(self)

    @property
    def internal_axes(self) -> Tuple[AxisConfig, ...]:
        return tuple(a for a in self.axes.values() if a.internal)

    @classmethod
    def load(cls, path: Union[str, Path]) -> "AxisTable":
        """Read a TOML axis table; :class:`ConfigError` names file, table and key."""
        from .config import load

        return load(Path(path))

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any], *, base_dir: Optional[Path] = None,
                     source: str = "axis table") -> "AxisTable":
        from .config import from_mapping

        return from_mapping(data, base_dir=base_dir, source=source)


IPR_KEY: Final = "increments_per_revolution"


def _validate(table: AxisTable) -> None:
    """The rules between axes; each message names the file, the axis table and the key."""
    src = table.source
    if not table.axes:
        raise ConfigError(f"{src}: no axes: add an [[axis]] table for each drive "
                          "(see example_axes.toml)")
    seen_nodes: Dict[Tuple[str, int], int] = {}
    external_seen = False
    for addr, axis in table.axes.items():
        where = f"{src}: [[axis]] AxAddr {addr}"
        if not 1 <= addr <= MAX_AXIS:
            raise ConfigError(f"{where}: addr: AxAddr {addr} is not 1..{MAX_AXIS} (spec 3)")
        # Spec 3.2: "make sure that all marked internal axes are at the beginning".
        if axis.internal and external_seen:
            raise ConfigError(f"{where}: internal: internal axis {addr} follows a "
                              "non-internal axis (spec 3.2)")
        external_seen = external_seen or not axis.internal
        if axis.device is DeviceCode.C_DC_MAXON_EPOS4 and axis.increments_per_revolution is None:
            raise ConfigError(f"{where}: {IPR_KEY}: device 5 (maxon EPOS4) needs it: the motor "
                              "encoder's increments per motor revolution (4 x pulses for an "
                              "incremental encoder), because an EPOS4 takes velocities in rpm")
        if not axis.has_node:
            if not axis.internal:
                raise ConfigError(f"{where}: node_id: 0 is only allowed for internal axes")
            continue
        limit = 65535 if axis.bus_offset is BusOffset.ETHERCAT else 127
        if not 1 <= axis.node_id <= limit:
            raise ConfigError(f"{where}: node_id: {axis.node_id} is not 1..{limit} (spec 3.4)")
        if axis.bus not in table.buses:
            raise ConfigError(f"{where}: bus_offset: the axis is on bus {axis.bus!r} (bus_offset "
                              f"{int(axis.bus_offset)}) but there is no [bus.{axis.bus}]")
        key = (axis.bus, axis.node_id)
        if key in seen_nodes:
            raise ConfigError(f"{where}: node_id: axes {seen_nodes[key]} and {addr} share node "
                              f"{axis.node_id} on {axis.bus}")
        seen_nodes[key] = addr
        slave = axis.parameters.get(29, 0)
        if slave and (slave == addr or slave not in table.axes):
            raise ConfigError(f"{where}: parameters.slave_axis: slave axis {slave} is not "
                              "another configured axis")
    _validate_cyclic(table)


CYCLIC_MODES: Final = ("csp",)
PROFILES: Final = ("bridge", "drive")  # the axis key profile (tables.config)
# The position window of an axis whose drive has no 6067h, in increments: the EPOS4's
# own default of 6067h (epos4.eds, DefaultValue=10).
DEFAULT_POSITION_WINDOW: Final = 10


def _validate_cyclic(table: AxisTable) -> None:
    """Internal axes in a cyclic mode (docs/bridge.md, "Internal axes in CSP")."""
    src = table.source
    cyclic = [a for a in table.axes.values() if a.cyclic is not None]
    for axis in cyclic:
        where = f"{src}: [[axis]] AxAddr {axis.addr}: cyclic"
        if axis.cyclic not in CYCLIC_MODES:
            raise ConfigError(f"{where}: {axis.cyclic!r} is not one of "
                              f"{', '.join(repr(m) for m in CYCLIC_MODES)}")
        if not axis.internal or not axis.has_node:
            raise ConfigError(f"{where}: only an internal axis with a drive (internal = true, "
                              "node_id set) is moved by the bridge's own profile (spec 3.2); "
                              "remove profile/cyclic from this axis")
    if not cyclic:
        return
    # Chosen: command 90 moves all internal axes with a drive on one line, through one
    # cyclic thread: so they are all cyclic, on one bus (one clock, one worker).
    driven = [a for a in table.internal_axes if a.has_node]
    plain = [a.addr for a in driven if a.cyclic is None]
    if plain:
        raise ConfigError(f"{src}: [[axis]] AxAddr {plain[0]}: profile: the internal axes "
                          f"{[a.addr for a in cyclic]} are moved in CSP by the bridge, so every "
                          "internal axis with a drive must be (command 90 moves them on one "
                          "line): write profile = \"drive\" on all of them, or on none")
    buses = sorted({a.bus for a in cyclic})
    if len(buses) > 1:
        raise ConfigError(f"{src}: [[axis]] cyclic: the cyclic internal axes are on buses "
                          f"{buses}; they must share one bus (one set-point thread)")


def simulated_table(count: int = 1, *, state_file: Optional[Path] = None,
                    bus_options: Optional[Mapping[str, Any]] = None,
                    ethercat_interface: Optional[str] = None,
                    ethercat_slaves: int = 0) -> AxisTable:
    """``count`` simulated EPOS4 drives: node 1 is the gateway itself, 2..count behind it.

    Position factor 1000: the simulator counts increments, so user units are
    mm at 1000 inc/mm. ``increments_per_revolution`` is the simulated encoder's
    (3000h/05h of the simulator's object dictionary).

    With ``ethercat_slaves`` N and the master's ``ethercat_interface``
    (:mod:`tcp_bridge.backends.ethercat_sim`): N more axes, AxAddr count+1..count+N,
    on bus ``ethercat`` (bus offset 1000000, spec 3.3), node id = slave position 1..N.
    """
    if not 1 <= count <= MAX_AXIS:
        raise ConfigError(f"--axes must be 1..{MAX_AXIS}, not {count}")
    if ethercat_slaves and count + ethercat_slaves > MAX_AXIS:
        raise ConfigError(f"--axes {count} and --ethercat {ethercat_slaves} make "
                          f"{count + ethercat_slaves} axes; at most {MAX_AXIS} (spec 3)")
    ipr = simulated_increments_per_revolution()
    axes = {
        n: AxisConfig(n, DeviceCode.C_DC_MAXON_EPOS4, False, BusOffset.CAN1, n, 1000,
                      MappingProxyType({}), ipr)
        for n in range(1, count + 1)
    }
    buses = {"can1": BusConfig("can1", "sim", MappingProxyType(dict(bus_options or {})))}
    if ethercat_slaves:
        for slave in range(1, ethercat_slaves + 1):
            axes[count + slave] = AxisConfig(count + slave, DeviceCode.C_DC_MAXON_EPOS4, False,
                                             BusOffset.ETHERCAT, slave, 1000,
                                             MappingProxyType({}), ipr)
        buses["ethercat"] = BusConfig("ethercat", "ethercat", MappingProxyType(
            {"interface": ethercat_interface, "cycle_ms": 4}))
    return AxisTable(MappingProxyType(axes), MappingProxyType(buses),
                     Settings(state_file=state_file))


def simulated_increments_per_revolution() -> int:
    """The main sensor resolution of the simulated EPOS4 (3000h/05h, EDS default)."""
    from canopen.objectdictionary import ODArray, ODRecord

    from epos_link.simulator.od import load_object_dictionary

    od = load_object_dictionary()
    try:
        sensor = od[0x3000]
        if not isinstance(sensor, (ODRecord, ODArray)):  # a VAR: no sensor record
            raise KeyError(0x3000)
        return int(sensor[5].default or 0)
    except KeyError:
        # A simulator whose EDS has no sensor objects counts velocities in inc/s:
        # 60 makes its "rpm" equal to inc/s at any factor (rpm = user*factor*60/ipr).
        return 60
