"""ACKs that survive ``kill -9``: ``python bench/killed_writes.py [--trials 30]``.

Issue 35. Each trial runs ``tcp-bridge serve --simulate --state-file F`` as its
own process; one client sends back-to-back ``2S05=<n>`` (n counting up, the
next only once the last was answered) while the bridge is killed with SIGKILL
at a random instant. Then the bridge is started again on the same state file and
asked ``2R05``. With durable-before-ACK (tcp_bridge/tables/statefile.py) the
value it reports is the last ACK'd one, or the one after it: the write in
flight when the bridge died, on disk, whose ACK never reached the client. An
older value means an ACK'd write was lost. After the restart, no temporary
file (``.F.*.tmp``) may be left beside the state file.

Reported: trials, how many restarted with the last ACK'd value, with the value
in flight, with an older one (lost ACK'd writes), temporaries left before the
restart (by the killed writer) and after it, and ACK'd writes per trial. Exit
status 1 if any ACK'd write was lost or a temporary was left after a restart.
The suite runs three trials (tests/test_state_durable.py).
"""
from __future__ import annotations

import argparse
import os
import random
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Optional

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from tcp_bridge.wire import REPLY_SIZE, Status, decode_reply  # noqa: E402

AXIS = 2  # a drive behind the simulated EPOS4's gateway: S05 writes its 6081h


class Bridge:
    """``tcp-bridge serve --simulate --state-file`` in its own process."""

    def __init__(self, state: Path) -> None:
        self.log = tempfile.TemporaryFile(mode="w+")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "tcp_bridge.cli", "serve", "--simulate", "--state-file",
             str(state), "--port", "0", "--maintenance-port", "-1"],
            stdout=subprocess.PIPE, stderr=self.log, text=True, cwd=ROOT)
        line = self.proc.stdout.readline()  # type: ignore[union-attr]
        if "listening on 127.0.0.1:" not in line:
            self.stop()
            self.log.seek(0)
            raise RuntimeError(f"the bridge did not start: {line!r} {self.log.read()!r}")
        self.port = int(line.split("127.0.0.1:")[1].split()[0])

    def ask(self, line: str, timeout: float = 30.0) -> str:
        with socket.create_connection(("127.0.0.1", self.port), timeout=timeout) as s:
            s.sendall(line.encode() + b"\r")
            reply = _recv(s)
        assert reply is not None, f"{line}: no reply"
        answer = decode_reply(reply)
        assert answer.status is Status.ACK, (line, answer)
        return answer.value or ""

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)


def _recv(s: socket.socket) -> Optional[bytes]:
    data = b""
    while len(data) < REPLY_SIZE:
        try:
            chunk = s.recv(REPLY_SIZE - len(data))
        except (ConnectionError, OSError):
            return None
        if not chunk:
            return None
        data += chunk
    return data


def temporaries(state: Path) -> List[str]:
    return sorted(p.name for p in state.parent.iterdir()
                  if p.name.startswith(f".{state.name}.") and p.name.endswith(".tmp"))


@dataclass
class Trial:
    acked: int = 0  # ACK'd writes
    last_acked: Optional[int] = None
    last_sent: Optional[int] = None
    restarted: Optional[int] = None  # the value 2R05 gave after the restart
    temporaries_killed: List[str] = field(default_factory=list)  # left by the killed bridge
    temporaries_after: List[str] = field(default_factory=list)  # left after the restart

    @property
    def verdict(self) -> str:
        """What the restarted bridge had (temporaries are counted apart)."""
        if self.last_acked is None:
            return "no ACK before the kill"
        if self.restarted == self.last_acked:
            return "last ACK'd"
        if self.restarted == self.last_sent:
            return "in flight"
        return "LOST"


def trial(directory: Path, rng: random.Random, base: int) -> Trial:
    state = directory / "state.json"
    result = Trial()
    bridge = Bridge(state)
    try:
        bridge.ask(f"{AXIS}S05={base}")  # one ACK'd value before the back-to-back writes
        result.acked, result.last_acked, result.last_sent = 1, base, base
        killer = threading.Timer(rng.uniform(0.2, 1.2),
                                 lambda: bridge.proc.send_signal(signal.SIGKILL))
        with socket.create_connection(("127.0.0.1", bridge.port), timeout=30) as s:
            killer.start()
            n = base
            while True:
                n += 1
                try:
                    s.sendall(f"{AXIS}S05={n}\r".encode())
                except OSError:
                    break
                result.last_sent = n
                reply = _recv(s)
                if reply is None:
                    break  # killed
                answer = decode_reply(reply)
                if answer.status is not Status.ACK:
                    raise RuntimeError(f"{AXIS}S05={n}: {answer}")
                result.acked += 1
                result.last_acked = n
        killer.join()
        bridge.proc.wait(30)
    finally:
        bridge.stop()
    result.temporaries_killed = temporaries(state)
    again = Bridge(state)
    try:
        result.temporaries_after = temporaries(state)
        result.restarted = int(again.ask(f"{AXIS}R05"))
    finally:
        again.stop()
    return result


def run(trials: int, seed: int, out: "Optional[List[str]]" = None) -> List[Trial]:
    rng = random.Random(seed)
    results: List[Trial] = []
    for i in range(trials):
        with tempfile.TemporaryDirectory(prefix="killed-writes-") as tmp:
            t = trial(Path(tmp), rng, base=1000 * (i + 1))
        results.append(t)
        line = (f"trial {i + 1:2d}: {t.acked:4d} ACK'd, last {t.last_acked}, sent {t.last_sent}, "
                f"restarted with {t.restarted}: {t.verdict}; temporaries left by the kill "
                f"{len(t.temporaries_killed)}, after the restart {len(t.temporaries_after)}")
        print(line, flush=True)
        if out is not None:
            out.append(line)
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=30)
    parser.add_argument("--seed", type=int, default=35)
    args = parser.parse_args()
    if args.trials < 1:
        parser.error("--trials: must be a positive number")
    start = time.monotonic()
    results = run(args.trials, args.seed)
    verdicts = [t.verdict for t in results]
    lost = verdicts.count("LOST")
    left = sum(1 for t in results if t.temporaries_after)
    acked = sorted(t.acked for t in results)
    exact = verdicts.count("last ACK'd")
    print(f"{len(results)} trials in {time.monotonic() - start:.0f} s: last ACK'd value "
          f"{exact}, the write in flight "
          f"{verdicts.count('in flight')}, older (ACK'd writes lost) {lost}; temporaries left by "
          f"the killed bridge in {sum(1 for t in results if t.temporaries_killed)} trials, "
          f"after the restart in {left}; ACK'd writes per trial: median {acked[len(acked) // 2]}")
    print(f"goal: 0 ACK'd writes lost, 0 temporaries after a restart: "
          f"{'met' if lost == 0 and left == 0 else 'NOT met'}")
    sys.exit(1 if lost or left else 0)


if __name__ == "__main__":
    main()
