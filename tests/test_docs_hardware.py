"""docs/hardware.md: linked from the README, its axis tables load, no world-writable udev rule."""
from __future__ import annotations

import re
import sys
from pathlib import Path

import pytest

from epos_link.transports.usb import PERMISSION_HELP, UDEV_RULE, UDEV_RULES_FILE
from tcp_bridge.tables.axes import AxisTable, simulated_increments_per_revolution

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

ROOT = Path(__file__).resolve().parent.parent
DOC = ROOT / "docs" / "hardware.md"


def blocks(language: str) -> list[str]:
    return re.findall(rf"```{language}\n(.*?)```", DOC.read_text(), re.S)


def test_the_readme_links_the_hardware_guide() -> None:
    assert "](docs/hardware.md)" in (ROOT / "README.md").read_text()


@pytest.mark.parametrize("text", blocks("toml"), ids=lambda t: t.split("\n")[0])
def test_every_axis_table_of_the_guide_loads(text: str) -> None:
    data = tomllib.loads(text)
    if "axis" not in data:  # a [bus.*] fragment: give it one axis to be a table
        data["axis"] = [{"node_id": 1}]
    table = AxisTable.from_mapping(data)
    assert table.buses


@pytest.mark.parametrize("path", ["README.md", "docs/hardware.md", "docs/epos-link.md",
                                  "epos_link/transports/usb.py", "epos_link/tools/ports.py"])
def test_no_world_writable_udev_rule(path: str) -> None:
    text = (ROOT / path).read_text()
    assert not re.search(r'MODE\s*=\s*"0?666"', text)
    assert "99-epos4" not in text


def test_the_uaccess_rule_sorts_before_seat_late() -> None:
    """systemd's 73-seat-late.rules applies the uaccess tag: a later file is too late."""
    assert 'TAG+="uaccess"' in UDEV_RULE and UDEV_RULE in PERMISSION_HELP
    name = Path(UDEV_RULES_FILE).name
    assert name < "73-seat-late.rules"
    assert UDEV_RULE in DOC.read_text() and name in DOC.read_text()


ECAT_EXAMPLE = ROOT / "tcp_bridge" / "example_ecat_axes.toml"


def test_the_guides_ethercat_table_is_the_shipped_one_and_fits_the_simulator() -> None:
    """Issue 34 item 7: the walkthrough's ``tcp-bridge check --config ecat-axes.toml``
    named a file that was not shipped, and the page's EtherCAT table (2048 inc/rev) did
    not run on the simulator (2000). The page shows the shipped file, which loads, names
    the walkthrough's veth end and the simulator's encoder
    (tests/test_bridge_ethercat_veth.py checks it against the simulated slave)."""
    ethercat = [t for t in blocks("toml") if 'backend = "ethercat"' in t and "[[axis]]" in t]
    assert ethercat == [ECAT_EXAMPLE.read_text()]
    table = AxisTable.load(ECAT_EXAMPLE)
    assert table.buses["ethercat"].backend == "ethercat"
    assert table.buses["ethercat"].options["interface"] == "ecm0"
    walkthrough = [b for b in blocks("sh") if "--ethercat ecs0" in b]
    assert len(walkthrough) == 1 and "ip link add ecm0 type veth peer name ecs0" in walkthrough[0]
    assert "tcp-bridge check --config tcp_bridge/example_ecat_axes.toml" in walkthrough[0]
    assert [a.increments_per_revolution for a in table.axes.values()] == [
        simulated_increments_per_revolution()]
