"""Reading the axis table from TOML: every mistake is one line naming file, table and key.

Policy (issue 12): a configuration is checked completely at start-up, and a
mistake ends the start with :class:`~tcp_bridge.tables.axes.ConfigError`, which the
CLI prints as one line and exit status 2. The line has the form::

    axes.toml: [[axis]] #2 (AxAddr 3): node_id: 200 is not 1..127 (spec 3.4)
    axes.toml: [bridge]: unknown key 'ack_timout' (did you mean 'ack_timeout'?)

Every value is type-checked before it is used, so no shape of TOML (a table
where an array of tables belongs, ``parameters = 5``, a string where a
number belongs, ``[bus] can1 = "sim"``, a file that is not UTF-8) can reach a
``dict()`` or a comparison and end in a traceback. A misspelt key gets the
nearest known key as a suggestion (``difflib``). What the keys mean is
documented in ``tcp_bridge/example_axes.toml``; the rules that relate axes to
each other (node ids, buses, spec 3.2 ordering) are in
:func:`tcp_bridge.tables.axes._validate`.
"""
from __future__ import annotations

import difflib
import math
import sys
from decimal import Decimal
from pathlib import Path
from types import MappingProxyType
from typing import Any, Dict, Iterable, Mapping, Optional

from ..access import parse_network
from .axes import (BUS_NAMES, DEVICE_NAMES, IPR_KEY, PROFILES, PARAMETER_NAMES, PARAMETER_NUMBERS,
                   AxisConfig, AxisTable, BusConfig, BusOffset, ConfigError, DeviceCode,
                   Settings, parameter_spec, to_stored)
from ..errors import InvalidCommand
from .bus_options import option_problem
from .units import Number, parse_value

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised on 3.10 only
    import tomli as tomllib  # type: ignore[import-not-found, no-redef, unused-ignore]

TOP_LEVEL = ("bridge", "bus", "axis", "epics")
AXIS_KEYS = ("addr", "device", "internal", "bus_offset", "node_id", "position_factor",
             "parameters", IPR_KEY, "profile", "cyclic", "position_window", "epics_name")
EPICS_KEYS = ("prefix",)  # [epics]: tcp_bridge.epics
# [bridge] keys: (check, description) by name; state_file and allow are special.
POSITIVE = ("ack_timeout", "state_timeout", "reset_timeout", "idle_timeout", "probe_interval")
NON_NEGATIVE = ("reset_delay", "poll_interval")
BRIDGE_KEYS = (*POSITIVE, *NON_NEGATIVE, "debug", "state_file", "allow")


def load(path: Path) -> AxisTable:
    """Read and check a TOML axis table."""
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise ConfigError(f"cannot read axis table {path}: {exc.strerror or exc}") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text (byte 0x{raw[exc.start]:02X} at offset "
                          f"{exc.start}); TOML files are UTF-8") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: {exc}") from None
    return from_mapping(data, base_dir=path.parent, source=str(path))


def suggest(key: str, known: Iterable[str]) -> str:
    """`` (did you mean 'x'?)`` for the nearest known key, or ``""``."""
    close = difflib.get_close_matches(str(key), list(known), n=1, cutoff=0.6)
    return f" (did you mean {close[0]!r}?)" if close else ""


def check_keys(raw: Mapping[str, Any], known: Iterable[str], where: str) -> None:
    known = list(known)
    unknown = sorted(str(k) for k in raw if k not in known)
    if unknown:
        key = unknown[0]
        raise ConfigError(f"{where}: unknown key {key!r}{suggest(key, known)}; "
                          f"known: {', '.join(known)}")


def _table(value: Any, where: str, hint: str = "") -> Dict[str, Any]:
    if not isinstance(value, dict):
        raise ConfigError(f"{where} must be a table, not {_shown(value)}{hint}")
    return dict(value)


def _shown(value: Any) -> str:
    if isinstance(value, dict):
        return "a table"
    if isinstance(value, list):
        return "an array"
    if isinstance(value, bool):
        return f"the boolean {str(value).lower()}"
    text = repr(value)
    return f"{type(value).__name__} {text if len(text) <= 40 else text[:37] + '...'}"


def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _integer(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def from_mapping(data: Mapping[str, Any], *, base_dir: Optional[Path] = None,
                 source: str = "axis table") -> AxisTable:
    """Check and convert a parsed TOML document; :class:`ConfigError` names the problem."""
    data = _table(data, source)
    check_keys(data, TOP_LEVEL, f"{source}: top level")
    settings = _settings(_table(data.get("bridge", {}), f"{source}: [bridge]"), base_dir, source)
    buses = _buses(data.get("bus", {}), source)
    rows = data.get("axis", [])
    if isinstance(rows, dict):
        raise ConfigError(f"{source}: [axis] is a single table; write [[axis]] (two brackets) "
                          "before each axis")
    if not isinstance(rows, list):
        raise ConfigError(f"{source}: axis must be an array of tables ([[axis]]), not "
                          f"{_shown(rows)}")
    if not rows:
        raise ConfigError(f"{source}: no axes: add an [[axis]] table for each drive "
                          "(see example_axes.toml)")
    axes: Dict[int, AxisConfig] = {}
    for position, row in enumerate(rows, start=1):
        where = f"{source}: [[axis]] #{position}"
        axis = _axis(_table(row, where), position, where)
        if axis.addr in axes:
            raise ConfigError(f"{where}: addr: AxAddr {axis.addr} appears twice")
        axes[axis.addr] = axis
    return AxisTable(MappingProxyType(dict(sorted(axes.items()))), MappingProxyType(buses),
                     settings, source=source,
                     epics_prefix=_epics(data.get("epics", {}), f"{source}: [epics]"))


def _epics(value: Any, where: str) -> Optional[str]:
    """``[epics] prefix = "LAB:"``: serve every axis as a motor record (tcp_bridge.epics)."""
    from ..epics.names import check_part  # pure

    raw = _table(value, where)
    check_keys(raw, EPICS_KEYS, where)
    if "prefix" not in raw:
        return None
    return check_part(raw["prefix"], f"{where}: prefix")


def _buses(value: Any, source: str) -> Dict[str, BusConfig]:
    raw = _table(value, f"{source}: [bus]")
    buses = {}
    for name, opts in raw.items():
        where = f"{source}: [bus.{name}]"
        if name not in BUS_NAMES.values():
            raise ConfigError(f"{where}: bus {name!r} is not one of "
                              f"{', '.join(sorted(BUS_NAMES.values()))}{suggest(name, BUS_NAMES.values())}")
        opts = _table(opts, where, f" (write [bus.{name}] with backend = \"...\" inside)")
        backend = opts.pop("backend", None)
        if not isinstance(backend, str):
            raise ConfigError(f"{where}: backend: needs backend = \"canopen\"|\"epos\"|\"sim\"")
        from ..backends import known_backends  # lazily: the registry imports this package

        known_names = known_backends()
        if backend not in known_names:  # a typo is the table's mistake: said here, with its place
            raise ConfigError(f"{where}: backend: unknown backend {backend!r}"
                              f"{suggest(backend, known_names)}; known: {', '.join(known_names)}")
        for key, value in opts.items():
            problem = option_problem(backend, key, value)
            if problem:
                raise ConfigError(f"{where}: {key}: {problem}, not {_shown(value)}")
        buses[name] = BusConfig(name, backend, MappingProxyType(opts))
    return buses


def _settings(raw: Dict[str, Any], base_dir: Optional[Path], source: str) -> Settings:
    where = f"{source}: [bridge]"
    check_keys(raw, BRIDGE_KEYS, where)
    values: Dict[str, Any] = {}
    for key, value in raw.items():
        if key in POSITIVE and not (_number(value) and value > 0):
            raise ConfigError(f"{where}: {key}: must be a positive number of seconds, not "
                              f"{_shown(value)}")
        if key in NON_NEGATIVE and not (_number(value) and value >= 0):
            raise ConfigError(f"{where}: {key}: must be a number of seconds, 0 or more, not "
                              f"{_shown(value)}")
        if key == "debug" and not isinstance(value, bool):
            raise ConfigError(f"{where}: debug: must be true or false, not {_shown(value)}")
        if key == "state_file":
            if not isinstance(value, str) or not value.strip():
                raise ConfigError(f"{where}: state_file: must be a file name, not {_shown(value)}")
            path = Path(value)
            if not path.is_absolute() and base_dir is not None:
                path = base_dir / path
            value = path
        if key == "allow":
            # A list, always: a lone string would be one network where a list of them
            # was meant (issue 35), so it is the wrong type like any other.
            if not isinstance(value, list) or not value:
                raise ConfigError(f"{where}: allow: must be a list of networks such as "
                                  f"[\"10.1.2.0/24\"], not {_shown(value)}")
            try:
                value = tuple(parse_network(v) for v in value)
            except ValueError as exc:
                raise ConfigError(f"{where}: allow: {exc}") from None
        values[key] = float(value) if key in POSITIVE + NON_NEGATIVE else value
    return Settings(**values)


def _axis(row: Dict[str, Any], position: int, where: str) -> AxisConfig:
    check_keys(row, AXIS_KEYS, where)
    addr = row.get("addr", position)  # spec 3.1: filled in from the position
    if not _integer(addr):
        raise ConfigError(f"{where}: addr: must be an integer 1..60, not {_shown(addr)}")
    where = f"{where} (AxAddr {addr})"
    device = row.get("device", 0)
    if isinstance(device, str):
        name = device.lower()
        if name not in DEVICE_NAMES:
            raise ConfigError(f"{where}: device: {device!r} is not one of "
                              f"{', '.join(sorted(DEVICE_NAMES))}{suggest(name, DEVICE_NAMES)}")
        device = DEVICE_NAMES[name]
    if not _integer(device) or device not in set(DeviceCode):
        raise ConfigError(f"{where}: device: {_shown(device)} is not a valid DeviceCode "
                          f"({', '.join(str(int(c)) for c in DeviceCode)} or a name)")
    bus_offset = row.get("bus_offset", 0)
    if not _integer(bus_offset) or bus_offset not in set(BusOffset):
        raise ConfigError(f"{where}: bus_offset: {_shown(bus_offset)} is not a valid BusOffset "
                          f"({', '.join(str(int(b)) for b in BusOffset)}, spec 3.3)")
    factor = row.get("position_factor", 1)
    if not _integer(factor) or factor <= 0:
        raise ConfigError(f"{where}: position_factor: must be a positive integer, not "
                          f"{_shown(factor)}")
    internal = row.get("internal", False)
    if not isinstance(internal, bool):
        raise ConfigError(f"{where}: internal: must be true or false, not {_shown(internal)}")
    node_id = row.get("node_id", 0)
    if not _integer(node_id):
        raise ConfigError(f"{where}: node_id: must be an integer, not {_shown(node_id)}")
    ipr = row.get(IPR_KEY)
    if ipr is not None and (not _integer(ipr) or ipr <= 0):
        raise ConfigError(f"{where}: {IPR_KEY}: must be a positive integer, not {_shown(ipr)}")
    params = _parameters(_table(row.get("parameters", {}), f"{where}: parameters",
                                " (write [axis.parameters] below the [[axis]] it belongs to)"),
                         factor, where)
    cyclic = _profile(row, internal, node_id, where)
    window = row.get("position_window")
    if window is not None and (not _integer(window) or not 0 <= window <= 0xFFFFFFFF):
        raise ConfigError(f"{where}: position_window: must be increments 0..4294967295, not "
                          f"{_shown(window)}")
    epics_name = row.get("epics_name")
    if epics_name is not None:
        from ..epics.names import check_part  # pure

        check_part(epics_name, f"{where}: epics_name")
    return AxisConfig(addr, DeviceCode(device), internal, BusOffset(bus_offset), node_id, factor,
                      MappingProxyType(params), ipr, cyclic, epics_name, position_window=window)


def _profile(row: Dict[str, Any], internal: bool, node_id: Any, where: str) -> Optional[str]:
    """PSI spec 3.2: an internal axis with a drive is moved by the bridge's profile in CSP
    (CSV for velocity moves) unless ``profile = "drive"`` keeps the drive's own profile
    modes. The key of issue 26, ``cyclic = "csp"``, still means "bridge"."""
    profile = row.get("profile")
    if profile is not None and profile not in PROFILES:
        raise ConfigError(f"{where}: profile: must be \"bridge\" (CSP/CSV, the default of an "
                          f"internal axis with a drive) or \"drive\" (its own profile modes), "
                          f"not {_shown(profile)}")
    if "cyclic" in row:
        cyclic = row["cyclic"]
        if cyclic != "csp":
            raise ConfigError(f"{where}: cyclic: {_shown(cyclic)} is not a value of this key; "
                              "an internal axis is moved in CSP by default now: remove cyclic, "
                              "or write profile = \"drive\" for the drive's own profile modes")
        if profile == "drive":
            raise ConfigError(f"{where}: cyclic = \"csp\" and profile = \"drive\" contradict "
                              "each other: keep one (cyclic is the old name of profile = "
                              "\"bridge\")")
        return "csp"  # checked against internal/node_id with the table (axes._validate_cyclic)
    if profile == "bridge":
        return "csp"
    if profile is None and internal and node_id != 0:
        return "csp"
    return None


def _parameters(raw: Dict[str, Any], factor: int, where: str) -> Dict[int, Number]:
    out: Dict[int, Number] = {}
    known = list(PARAMETER_NUMBERS)
    for key, value in raw.items():
        cmd = PARAMETER_NUMBERS.get(key)
        if cmd is None and key.isdigit() and int(key) in PARAMETER_NAMES:
            cmd = int(key)
        if cmd is None or cmd == 19:
            hint = " (the device code is the axis key 'device')" if cmd == 19 or key == "device_code" \
                else suggest(key, known)
            raise ConfigError(f"{where}: parameters.{key}: unknown parameter {key!r}{hint}")
        if not _number(value):
            raise ConfigError(f"{where}: parameters.{key}: must be a number, not {_shown(value)}")
        text = str(value) if isinstance(value, int) else format(Decimal(repr(value)), "f")
        spec = parameter_spec(cmd)
        try:
            user = parse_value(spec, text)
            to_stored(spec, user, factor)  # range check of the scaled value
        except InvalidCommand as exc:
            raise ConfigError(f"{where}: parameters.{key}: {exc}") from None
        out[cmd] = user
    return out
