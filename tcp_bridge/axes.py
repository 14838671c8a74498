"""The axis table of the gateway (spec section 3) and its parameter array.

Spec 3: "the axis settings and the axis parameters are stored in an array. For
each axis there is an array and the system supports up to 60 axes." An axis is
``AxAddr`` (3.1), a device code (3.5), the internal flag (3.2), a bus offset
(3.3), a node id (3.4) and the position user-unit factor (3.6). The parameters
are the internal parameters of the command table (spec 4), kept here by TCP
command number (2, 5, 6, 19..63, 80) in their stored form: an integer, and for
the ``*`` ones ``round(user value * factor)`` (spec 4 footnote).

The table is read from a TOML file; ``tcp_bridge/example_axes.toml`` documents
every key. Parameters changed with S commands are kept in a JSON state file,
written atomically (temporary file, fsync, rename) after every change and
overlaid on the TOML values at start, as the controller keeps them in its
arrays across restarts.

Device codes: spec 3.5 defines 0..4. This bridge adds
``C_DC_MAXON_EPOS4 = 5`` for the maxon EPOS4 (a plain CiA 402 drive: position
read from 6064h, detailed error from 603Fh, see :mod:`tcp_bridge.engine`).
"""
from __future__ import annotations

import sys
from dataclasses import dataclass, field
from decimal import Decimal
from enum import IntEnum
from pathlib import Path
from types import MappingProxyType
from typing import Any, Dict, Final, Mapping, Optional, Tuple, Union

from .commands import COMMANDS, CommandKind, CommandSpec
from .errors import BridgeError, InvalidCommand
from .protocol import MAX_AXIS
from .units import Number, Scaling, parse_value, stored_parameter

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised on 3.10 only
    import tomli as tomllib


class ConfigError(BridgeError, ValueError):
    """The axis table or the state file is not valid; raised at start-up only."""


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
    # quadrature (4 x 3010h/01h pulses); velocities are rpm (tcp_bridge.units).
    increments_per_revolution: Optional[int] = None

    @property
    def bus(self) -> str:
        return BUS_NAMES[self.bus_offset]

    @property
    def has_node(self) -> bool:
        """An internal axis with node id 0 is the controller's own (spec 3 example)."""
        return self.node_id != 0


@dataclass(frozen=True)
class Settings:
    """Timing and behaviour of the command layer (the ``[bridge]`` table)."""

    ack_timeout: float = 2.0  # bound for the ACK of 00 and 04 (drive acceptance)
    state_timeout: float = 1.0  # bound for one state machine step / mode change
    reset_timeout: float = 5.0  # bound for a node to answer again after NMT reset
    reset_delay: float = 0.3  # pause after the NMT reset before polling the node
    poll_interval: float = 0.002  # pause between statusword polls
    debug: bool = False  # initial value of command 91
    state_file: Optional[Path] = None

    def __post_init__(self) -> None:
        for name in ("ack_timeout", "state_timeout", "reset_timeout"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"[bridge] {name} must be positive")
        for name in ("reset_delay", "poll_interval"):
            if not getattr(self, name) >= 0:
                raise ConfigError(f"[bridge] {name} must not be negative")


@dataclass(frozen=True)
class AxisTable:
    """Axes by AxAddr, buses by name, settings."""

    axes: Mapping[int, AxisConfig]
    buses: Mapping[str, BusConfig]
    settings: Settings = Settings()

    def __post_init__(self) -> None:
        _validate(self)

    @property
    def internal_axes(self) -> Tuple[AxisConfig, ...]:
        return tuple(a for a in self.axes.values() if a.internal)

    @classmethod
    def load(cls, path: Union[str, Path]) -> "AxisTable":
        """Read a TOML axis table; :class:`ConfigError` names the problem."""
        path = Path(path)
        try:
            data = tomllib.loads(path.read_text(encoding="utf-8"))
        except OSError as exc:
            raise ConfigError(f"cannot read axis table {path}: {exc.strerror or exc}") from None
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"{path}: {exc}") from None
        return cls.from_mapping(data, base_dir=path.parent, source=str(path))

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any], *, base_dir: Optional[Path] = None,
                     source: str = "axis table") -> "AxisTable":
        unknown = set(data) - {"bridge", "bus", "axis"}
        if unknown:
            raise ConfigError(f"{source}: unknown top-level keys {sorted(unknown)}")
        settings = _settings(dict(data.get("bridge", {})), base_dir, source)
        buses = {}
        for name, opts in dict(data.get("bus", {})).items():
            if name not in BUS_NAMES.values():
                raise ConfigError(f"{source}: bus {name!r} is not one of {sorted(BUS_NAMES.values())}")
            opts = dict(opts)
            backend = opts.pop("backend", None)
            if not isinstance(backend, str):
                raise ConfigError(f"{source}: [bus.{name}] needs backend = \"canopen\"|\"epos\"|\"sim\"")
            buses[name] = BusConfig(name, backend, MappingProxyType(opts))
        axes: Dict[int, AxisConfig] = {}
        for position, row in enumerate(data.get("axis", []), start=1):
            axis = _axis(dict(row), position, source)
            if axis.addr in axes:
                raise ConfigError(f"{source}: AxAddr {axis.addr} appears twice")
            axes[axis.addr] = axis
        return cls(MappingProxyType(dict(sorted(axes.items()))), MappingProxyType(buses), settings)


def _settings(raw: Dict[str, Any], base_dir: Optional[Path], source: str) -> Settings:
    state = raw.pop("state_file", None)
    known = {f for f in Settings.__dataclass_fields__ if f != "state_file"}
    unknown = set(raw) - known
    if unknown:
        raise ConfigError(f"{source}: unknown [bridge] keys {sorted(unknown)}")
    state_path = None
    if state:
        state_path = Path(state)
        if not state_path.is_absolute() and base_dir is not None:
            state_path = base_dir / state_path
    try:
        return Settings(**raw, state_file=state_path)
    except TypeError as exc:
        raise ConfigError(f"{source}: [bridge]: {exc}") from None


_AXIS_KEYS: Final = {"addr", "device", "internal", "bus_offset", "node_id", "position_factor",
                     "parameters", "increments_per_revolution"}
IPR_KEY: Final = "increments_per_revolution"


def _axis(row: Dict[str, Any], position: int, source: str) -> AxisConfig:
    where = f"{source}: axis #{position}"
    unknown = set(row) - _AXIS_KEYS
    if unknown:
        raise ConfigError(f"{where}: unknown keys {sorted(unknown)}")
    addr = row.get("addr", position)  # spec 3.1: filled in from the position
    device = row.get("device", 0)
    if isinstance(device, str):
        if device.lower() not in DEVICE_NAMES:
            raise ConfigError(f"{where}: device {device!r} is not one of {sorted(DEVICE_NAMES)}")
        device = DEVICE_NAMES[device.lower()]
    try:
        device = DeviceCode(device)
        bus_offset = BusOffset(row.get("bus_offset", 0))
    except ValueError as exc:
        raise ConfigError(f"{where}: {exc}") from None
    factor = row.get("position_factor", 1)
    if isinstance(factor, bool) or not isinstance(factor, int) or factor <= 0:
        raise ConfigError(f"{where}: position_factor must be a positive integer")
    internal = row.get("internal", False)
    node_id = row.get("node_id", 0)
    if not isinstance(internal, bool) or not isinstance(addr, int) or not isinstance(node_id, int):
        raise ConfigError(f"{where}: addr and node_id are integers, internal is true/false")
    ipr = row.get(IPR_KEY)
    if ipr is not None and (isinstance(ipr, bool) or not isinstance(ipr, int) or ipr <= 0):
        raise ConfigError(f"{where} (AxAddr {addr}): {IPR_KEY} must be a positive integer")
    params = _parameters(dict(row.get("parameters", {})), factor, f"{where} (AxAddr {addr})")
    return AxisConfig(addr, device, internal, bus_offset, node_id, factor,
                      MappingProxyType(params), ipr)


def _parameters(raw: Dict[str, Any], factor: int, where: str) -> Dict[int, Number]:
    out: Dict[int, Number] = {}
    for key, value in raw.items():
        cmd = PARAMETER_NUMBERS.get(key)
        if cmd is None and key.isdigit() and int(key) in PARAMETER_NAMES:
            cmd = int(key)
        if cmd is None or cmd == 19:
            raise ConfigError(f"{where}: unknown parameter {key!r} (the device code is 'device')")
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: parameter {key} must be a number")
        text = str(value) if isinstance(value, int) else format(Decimal(repr(value)), "f")
        spec = parameter_spec(cmd)
        try:
            user = parse_value(spec, text)
            to_stored(spec, user, factor)  # range check of the scaled value
        except InvalidCommand as exc:
            raise ConfigError(f"{where}: parameter {key}: {exc}") from None
        out[cmd] = user
    return out


def _validate(table: AxisTable) -> None:
    seen_nodes: Dict[Tuple[str, int], int] = {}
    external_seen = False
    for addr, axis in table.axes.items():
        if not 1 <= addr <= MAX_AXIS:
            raise ConfigError(f"AxAddr {addr} is not 1..{MAX_AXIS} (spec 3)")
        # Spec 3.2: "make sure that all marked internal axes are at the beginning".
        if axis.internal and external_seen:
            raise ConfigError(f"internal axis {addr} follows a non-internal axis (spec 3.2)")
        external_seen = external_seen or not axis.internal
        if axis.device is DeviceCode.C_DC_MAXON_EPOS4 and axis.increments_per_revolution is None:
            raise ConfigError(f"axis {addr}: device 5 (maxon EPOS4) needs {IPR_KEY}: the motor "
                              "encoder's increments per motor revolution (4 x pulses for an "
                              "incremental encoder), because an EPOS4 takes velocities in rpm")
        if not axis.has_node:
            if not axis.internal:
                raise ConfigError(f"axis {addr}: node_id 0 is only allowed for internal axes")
            continue
        limit = 65535 if axis.bus_offset is BusOffset.ETHERCAT else 127
        if not 1 <= axis.node_id <= limit:
            raise ConfigError(f"axis {addr}: node_id {axis.node_id} is not 1..{limit} (spec 3.4)")
        if axis.bus not in table.buses:
            raise ConfigError(f"axis {addr} is on bus {axis.bus!r} (bus_offset "
                              f"{int(axis.bus_offset)}) but there is no [bus.{axis.bus}]")
        key = (axis.bus, axis.node_id)
        if key in seen_nodes:
            raise ConfigError(f"axes {seen_nodes[key]} and {addr} share node {axis.node_id} "
                              f"on {axis.bus}")
        seen_nodes[key] = addr
        slave = axis.parameters.get(29, 0)
        if slave and (slave == addr or slave not in table.axes):
            raise ConfigError(f"axis {addr}: slave axis {slave} is not another configured axis")


def simulated_table(count: int = 1, *, state_file: Optional[Path] = None,
                    bus_options: Optional[Mapping[str, Any]] = None) -> AxisTable:
    """``count`` simulated EPOS4 drives: node 1 is the gateway itself, 2..count behind it.

    Position factor 1000: the simulator counts increments, so user units are
    mm at 1000 inc/mm. ``increments_per_revolution`` is the simulated encoder's
    (3000h/05h of the simulator's object dictionary).
    """
    if not 1 <= count <= MAX_AXIS:
        raise ConfigError(f"--axes must be 1..{MAX_AXIS}, not {count}")
    ipr = simulated_increments_per_revolution()
    axes = {
        n: AxisConfig(n, DeviceCode.C_DC_MAXON_EPOS4, False, BusOffset.CAN1, n, 1000,
                      MappingProxyType({}), ipr)
        for n in range(1, count + 1)
    }
    bus = BusConfig("can1", "sim", MappingProxyType(dict(bus_options or {})))
    return AxisTable(MappingProxyType(axes), MappingProxyType({"can1": bus}),
                     Settings(state_file=state_file))


def simulated_increments_per_revolution() -> int:
    """The main sensor resolution of the simulated EPOS4 (3000h/05h, EDS default)."""
    from epos_link.simulator.od import load_object_dictionary

    od = load_object_dictionary()
    try:
        return int(od[0x3000][5].default)
    except KeyError:
        # A simulator whose EDS has no sensor objects counts velocities in inc/s:
        # 60 makes its "rpm" equal to inc/s at any factor (rpm = user*factor*60/ipr).
        return 60
