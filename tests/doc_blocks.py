"""The ```console blocks of README.md and docs/*.md, parsed and run (tests/test_docs_commands.py).

The convention, which docs authors follow (README.md repeats it in an HTML comment):

* A ```console block is a terminal session. A line starting with ``$ `` is a
  command; a command line ending in ``\\`` continues on the next line, and a
  heredoc (``<< 'EOF'``) runs to its terminator line. The lines after a command,
  up to the next ``$ ``, are its expected output (standard output and standard
  error together, as a terminal shows them; trailing blanks ignored).
* Output that varies: ``...`` inside a line matches any text; a line that is only
  ``...`` matches any number of lines, none included.
* A command ending in ``&`` starts a background process: the lines after it are
  the first lines it prints (the test waits up to 60 s for them), and it is
  stopped (SIGINT, then SIGKILL) when the block ends. A program that serves
  until stopped (``epos-link sim``, ``epos-link monitor``) must be shown with
  ``&``. ``sleep`` and ``echo $?`` work as in a shell (``$?`` is the previous
  command's status), and so does ``kill [-SIGNAL] %N``: it signals the process
  group of the block's Nth ``&`` command, as an interactive shell's job spec
  does (``kill -9 %2`` kills the second one, as a crash would), and ``wait %N`` waits
  for it to end (its status is ``$?``; what it prints meanwhile is not compared).
* The environment: an HTML comment on the line before the fence,
  ``<!-- doc-test: ENV -->``, where ENV is
  ``none`` (the default: the block brings what it needs, e.g. its own ``&``
  simulator); ``bridge-sim`` (a ``tcp-bridge serve --simulate`` with its default
  three axes, serving 127.0.0.1:1912 and :1913); ``sim-tcp`` (an ``epos-link sim
  --tcp 127.0.0.1:4001 --drives 2,3``); or ``skip: REASON`` (REASON must start
  with ``needs hardware``, ``needs root`` or ``tested by tests/FILE``). After
  ENV, ``, needs PROGRAM`` skips the block where PROGRAM is not installed.
  One bridge-sim and one sim-tcp serve all blocks of a test module, so blocks
  that share one must not write to the same axis or node: a block's outcome may
  not depend on which blocks ran before it.
* Every ``127.0.0.1:PORT`` (PORT not 0) of a block is rewritten, in its commands
  and outputs alike, to a free port the test picked (the environment's ports to
  its own), so the docs show memorable ports and tests run side by side. So is
  the PORT of a command's ``--port PORT`` and ``--maintenance-port PORT``
  (``tcp-bridge serve``'s listening ports).
* Commands run under bash in a fresh directory that holds links to the
  repository's top-level files (``fixtures/...``, ``tcp_bridge/example_axes.toml``
  resolve), ``NO_COLOR=1``, ``.venv/bin/`` mapped to this interpreter's scripts
  directory, and the checkout first on PYTHONPATH. Blocks fenced as ```sh, ```text
  etc. are not run.
* A block leaves no file in the checkout (issue 34: a reader who followed the pages
  found move.csv, cap.txt, drive2.dcf, ... in ``git status``): the files it writes
  go to ``/tmp/``, which is rewritten, in commands and outputs alike, to a scratch
  directory of the test's own (as ports are, so tests run side by side); HOME is a
  directory there and TMPDIR is it, so what programs put in /tmp themselves is there. tests/test_docs_commands.py fails a block that writes
  into its working directory (the reader's checkout) or changes ``git status``.
"""
from __future__ import annotations

import os
import queue
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
BIN = Path(sys.executable).parent
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
ENVIRONMENTS = ("none", "bridge-sim", "sim-tcp")
SKIP_REASONS = ("needs hardware", "needs root", "tested by tests/")
COMMAND_TIMEOUT = 120.0   # one command on a loaded machine; none takes more than a few s
BACKGROUND_WAIT = 60.0    # for a background process's first lines

FENCE = re.compile(r"^(\s*)```(\S*)\s*$")
TAG = re.compile(r"^\s*<!--\s*doc-test:\s*(.*?)\s*-->\s*$")
HEREDOC = re.compile(r"<<-?\s*(['\"]?)(\w+)\1")
BACKGROUND = re.compile(r"(?<![&>|])&\s*(#[^\n]*)?$")
ADDRESS = re.compile(r"\b(127\.0\.0\.1|localhost):(\d+)\b")
PORT_OPTION = re.compile(r"(--(?:maintenance-)?port[ =])(\d+)\b")
JOB_KILL = re.compile(r"^kill(?:\s+-(\w+))?\s+%(\d+)\s*(?:#.*)?$")
JOB_WAIT = re.compile(r"^wait\s+%(\d+)\s*(?:#.*)?$")
TMP = re.compile(r"(?<![\w./~-])/tmp/")


@dataclass
class Command:
    text: str
    line: int
    expected: list[str] = field(default_factory=list)

    @property
    def background(self) -> bool:
        return bool(BACKGROUND.search(self.text))


@dataclass
class Block:
    path: Path
    line: int
    env: str
    needs: list[str]
    commands: list[Command]

    @property
    def id(self) -> str:
        return f"{self.path.relative_to(ROOT)}:{self.line}"

    @property
    def skip(self) -> str | None:
        return self.env[len("skip:"):].strip() if self.env.startswith("skip:") else None


def parse(path: Path) -> list[Block]:
    lines = path.read_text().split("\n")
    blocks: list[Block] = []
    i = 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if not m or not m.group(2):
            i += 1
            continue
        indent, language, start = len(m.group(1)), m.group(2), i
        end = i + 1
        while end < len(lines) and not FENCE.match(lines[end]):
            end += 1
        if language == "console":
            body = [line[indent:] for line in lines[start + 1:end]]
            env, needs = tag(lines, start)
            blocks.append(Block(path, start + 1, env, needs, commands(body, start + 2)))
        i = end + 1
    return blocks


def tag(lines: list[str], fence: int) -> tuple[str, list[str]]:
    before = fence - 1
    while before >= 0 and not lines[before].strip():
        before -= 1
    m = TAG.match(lines[before]) if before >= 0 else None
    if not m:
        return "none", []
    env, *rest = [part.strip() for part in m.group(1).split(",")] if not m.group(1).startswith("skip:") \
        else [m.group(1)]
    return env, [r.removeprefix("needs").strip() for r in rest]


def commands(body: list[str], first_line: int) -> list[Command]:
    out: list[Command] = []
    i = 0
    while i < len(body):
        line = body[i]
        if not line.startswith("$ "):
            if out:
                out[-1].expected.append(line.rstrip())
            elif line.strip():
                raise ValueError(f"line {first_line + i}: output before the first command")
            i += 1
            continue
        text, start = line[2:], i
        while text.endswith("\\") and i + 1 < len(body):
            i += 1
            text += "\n" + body[i]
        heredoc = HEREDOC.search(text)
        if heredoc:
            while i + 1 < len(body):
                i += 1
                text += "\n" + body[i]
                if body[i] == heredoc.group(2):
                    break
        out.append(Command(text, first_line + start))
        i += 1
    for c in out:
        while c.expected and not c.expected[-1]:
            c.expected.pop()
    return out


def all_blocks() -> list[Block]:
    return [b for path in DOCS for b in parse(path)]


def matches(expected: list[str], actual: list[str]) -> bool:
    """``...`` alone on a line: any lines; ``...`` inside a line: any text."""
    # can[j]: actual[j:] matches the expected lines from the one being looked at on
    # (filled from the last expected line back: no recursion, whatever the length).
    can = [j == len(actual) for j in range(len(actual) + 1)]
    for head in reversed(expected):
        if head == "...":
            for j in range(len(actual) - 1, -1, -1):
                can[j] = can[j] or can[j + 1]
            continue
        pattern = re.compile(".*".join(re.escape(part) for part in head.split("...")))
        can = [j < len(actual) and pattern.fullmatch(actual[j]) is not None and can[j + 1]
               for j in range(len(actual) + 1)]
    return can[0]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def rewrite_ports(block: Block, given: dict[int, int]) -> dict[int, int]:
    """The block's port map: the environment's ports, then a free one for each other."""
    ports = dict(given)
    for c in block.commands:
        for m in [*ADDRESS.finditer(c.text), *PORT_OPTION.finditer(c.text)]:
            port = int(m.group(2))
            if port and port not in ports:
                ports[port] = free_port()
    return ports


def localise(text: str, ports: dict[int, int], scratch: Path | None = None) -> str:
    def address(m: re.Match[str]) -> str:
        port = int(m.group(2))
        return f"{m.group(1)}:{ports.get(port, port)}"

    def option(m: re.Match[str]) -> str:
        port = int(m.group(2))
        return f"{m.group(1)}{ports.get(port, port)}"
    text = PORT_OPTION.sub(option, ADDRESS.sub(address, text))
    if scratch is not None:
        text = TMP.sub(f"{scratch}/", text)
    return text.replace(".venv/bin/", f"{BIN}/")


def job_kill(text: str) -> tuple[signal.Signals, int] | None:
    """``kill [-SIGNAL] %N``: the signal (SIGTERM unless named) and N. None for any other
    command, and for a signal bash does not know (bash then says so itself)."""
    m = JOB_KILL.match(text.strip())
    if m is None:
        return None
    name = (m.group(1) or "TERM").upper()
    try:
        sig = signal.Signals(int(name)) if name.isdigit() else signal.Signals["SIG" + name.removeprefix("SIG")]
    except (KeyError, ValueError):
        return None
    return sig, int(m.group(2))


def environment(home: Path) -> dict[str, str]:
    env = dict(os.environ, HOME=str(home), NO_COLOR="1", LC_ALL="C.UTF-8")
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))
    env.pop("COLUMNS", None)
    return env


def workdir(tmp: Path) -> Path:
    for entry in ROOT.iterdir():
        if entry.name not in (".git", ".venv") and not (tmp / entry.name).exists():
            (tmp / entry.name).symlink_to(entry)
    return tmp


class Background:
    """A ``&`` command: its output collected by a thread, stopped with its process group."""

    def __init__(self, text: str, cwd: Path, env: dict[str, str]) -> None:
        self.proc = subprocess.Popen(["bash", "-c", text], cwd=cwd, env=env, text=True,
                                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                     stdin=subprocess.DEVNULL, start_new_session=True)
        self.lines: queue.Queue[str] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.put(line.rstrip())

    def first_lines(self, expected: list[str]) -> list[str]:
        """Lines until they match ``expected`` (followed by anything), or the wait ends."""
        seen: list[str] = []
        deadline = time.monotonic() + BACKGROUND_WAIT
        while not matches([*expected, "..."], seen):
            try:
                seen.append(self.lines.get(timeout=max(0.0, deadline - time.monotonic())))
            except queue.Empty:
                break
        return seen

    def ready_on(self, port: int) -> bool:
        """Whether 127.0.0.1:port accepts a connection before the wait ends (or the process exits)."""
        deadline = time.monotonic() + BACKGROUND_WAIT
        while time.monotonic() < deadline and self.proc.poll() is None:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1.0).close()
                return True
            except OSError:
                time.sleep(0.1)
        return False

    def stop(self) -> None:
        for sig, wait in ((signal.SIGINT, 10.0), (signal.SIGKILL, 10.0)):
            if self.proc.poll() is not None:
                return
            try:
                os.killpg(self.proc.pid, sig)
                self.proc.wait(wait)
            except (ProcessLookupError, subprocess.TimeoutExpired):
                pass


def signal_job(background: list[Background], sig: signal.Signals, n: int) -> tuple[list[str], int]:
    """A shell's ``kill -SIG %n``: the process group of the nth ``&`` command; what bash prints."""
    if not 1 <= n <= len(background):
        return [f"bash: kill: %{n}: no such job"], 1
    try:
        os.killpg(background[n - 1].proc.pid, sig)
    except ProcessLookupError:
        return [f"bash: kill: %{n}: no such job"], 1
    return [], 0


def wait_job(background: list[Background], n: int) -> tuple[list[str], int]:
    """A shell's ``wait %n``: until the nth ``&`` command ends; its status."""
    if not 1 <= n <= len(background):
        return [f"bash: wait: %{n}: no such job"], 127
    try:
        return [], background[n - 1].proc.wait(COMMAND_TIMEOUT)
    except subprocess.TimeoutExpired:
        return [f"(%{n} still running after {COMMAND_TIMEOUT:g} s)"], 127


def run(block: Block, ports: dict[int, int], cwd: Path, scratch: Path | None = None) -> list[str]:
    """Run every command in ``cwd``, ``/tmp/`` being ``scratch`` (default: a temporary
    directory, removed after); return a description of each mismatch (empty: it holds)."""
    own = scratch is None
    scratch = Path(tempfile.mkdtemp(prefix="doc-block-")) if scratch is None else scratch
    (scratch / "home").mkdir(parents=True, exist_ok=True)
    env = environment(scratch / "home")
    env["TMPDIR"] = str(scratch)  # a program's own temporary files (sim --usb's umockdev dir)
    failures: list[str] = []
    background: list[Background] = []
    status = 0
    try:
        for c in block.commands:
            text = localise(c.text, ports, scratch)
            expected = [localise(line, ports, scratch) for line in c.expected]
            kill = job_kill(text)
            waited = JOB_WAIT.match(text.strip())
            if kill is not None:
                actual, status = signal_job(background, *kill)
                ok = matches(expected, actual)
            elif waited is not None:
                actual, status = wait_job(background, int(waited.group(1)))
                ok = matches(expected, actual)
            elif c.background:
                job = Background(BACKGROUND.sub("", text), cwd, env)
                background.append(job)
                actual = job.first_lines(expected)
                ok = matches([*expected, "..."], actual)
                status = 0
            else:
                done = subprocess.run(["bash", "-c", f"(exit {status})\n{text}"], cwd=cwd, env=env,
                                      text=True, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                      stdin=subprocess.DEVNULL, timeout=COMMAND_TIMEOUT)
                status = done.returncode
                actual = done.stdout.rstrip("\n").split("\n") if done.stdout.strip() else []
                actual = [line.rstrip() for line in actual]
                ok = matches(expected, actual)
            if not ok:
                failures.append(f"{block.path.relative_to(ROOT)}:{c.line}: $ {text}\n"
                                "--- expected\n" + "\n".join(expected) +
                                "\n--- actual\n" + "\n".join(actual))
                break  # later commands build on this one
    finally:
        for job in background:
            job.stop()
        if own:
            shutil.rmtree(scratch, ignore_errors=True)
    return failures
