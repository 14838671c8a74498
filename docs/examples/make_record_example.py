"""Make docs/record-example.png: ``epos-link record`` of a simulated move.

Starts ``epos-link sim --tcp`` (drives 2 and 3 behind its gateway), starts
``epos-link record`` on node 2 (position, velocity, statusword every 5 ms,
triggered by the move's start, 0.1 s kept before it), then moves node 2 in
profile position mode to 20000 inc over CAN, as an application would
(examples/pp_move.py, through the simulator's socketcand server), and waits for
the recording. Writes the PNG into docs/ and the CSV and an HTML plot into
``--out`` (default: a temporary directory, printed).

    .venv/bin/python docs/examples/make_record_example.py [--out DIR]
"""
from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from examples.pp_move import move  # noqa: E402

NODE = 2
TARGET = 20000  # increments: 0.7 s at 1000 rpm, 10000 rpm/s (examples/pp_move.py)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=None, help="where the CSV and HTML go")
    parser.add_argument("--png", type=Path, default=ROOT / "docs" / "record-example.png",
                        help="the PNG (default docs/record-example.png)")
    args = parser.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="record-example-"))
    out.mkdir(parents=True, exist_ok=True)
    png = args.png.resolve()
    cli = [sys.executable, "-m", "epos_link"]
    sim = subprocess.Popen([*cli, "sim", "--tcp", "127.0.0.1:0", "--drives", "2,3",
                            "--can-server", "127.0.0.1:0"], cwd=ROOT, stdout=subprocess.PIPE, text=True)
    try:
        assert sim.stdout is not None
        found = re.search(r"socket://\S+", sim.stdout.readline())
        if not found:
            raise SystemExit("epos-link sim did not say where it listens")
        url = found.group(0)
        can = None
        while can is None:  # the lines after it: the drives, then the socketcand server
            line = sim.stdout.readline()
            if not line:
                raise SystemExit("epos-link sim did not say where its CAN bus is served")
            served = re.search(r"socketcand at (\S+)", line)
            can = served.group(1) if served else None
        record = subprocess.Popen([*cli, "record", url, "--node", str(NODE), "position_actual_value",
                                   "velocity_actual_value", "statusword", "--period", "0.005",
                                   "--duration", "1", "--pre", "0.1", "--trigger", "move",
                                   "--csv", str(out / "move.csv"), "--plot", str(png),
                                   "--plot", str(out / "move.html")],
                                  cwd=ROOT, stderr=subprocess.PIPE, text=True)
        assert record.stderr is not None
        print(record.stderr.readline(), end="")  # "waiting for the trigger ..."
        move(can, NODE, TARGET)  # the application moves the axis over CAN
        record.wait(timeout=60)
        print(record.stderr.read(), end="")
        if record.returncode:
            return record.returncode
    finally:
        sim.terminate()
        sim.wait(timeout=10)
    print(f"wrote {png} ({png.stat().st_size} bytes), {out / 'move.csv'}, {out / 'move.html'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
