"""canopen's own API through an EPOS4's USB/RS232 port, here the simulated one.

Run: .venv/bin/python examples/canopen_through_epos4.py [URL]
With a real EPOS4 pass its URL (e.g. /dev/ttyACM0 or usb://); without one the
script starts the simulator on a pseudo-terminal.
"""
import sys

from epos_link import connect_node

url = sys.argv[1] if len(sys.argv) > 1 else None
sim = link = None
if url is None:
    from epos_link.simulator.core import Epos4Simulator
    from epos_link.simulator.link import PtyLink

    sim = Epos4Simulator(node_id=1, drives=[2])
    link = PtyLink(sim).start()
    url = link.path

node = connect_node(url, 2, profile="402")       # node 2 sits behind the EPOS4 on CAN
node.nmt.state = "RESET"                          # as canopen scripts for a CAN adapter begin
node.nmt.wait_for_bootup(5)                       # through the gateway: until it answers SDO
print("device:", node.sdo["Manufacturer device name"].raw, "NMT:", node.nmt.state)
node.setup_402_state_machine()                    # PDO setup read by SDO; state machine on SDO
node.state = "OPERATION ENABLED"
node.op_mode = "PROFILED POSITION"
node.sdo["Profile velocity"].raw = 20000
node.sdo["Target position"].raw = 5000
node.controlword = 0x1F                          # new set-point, absolute
while not node.statusword & 0x1000:              # set-point acknowledge
    pass
node.controlword = 0x0F
while not node.statusword & 0x0400:              # target reached
    pass
print("position:", node.sdo["Position actual value"].raw)
node.state = "SWITCH ON DISABLED"
node.close()
if link:
    link.close()
    sim.close()
