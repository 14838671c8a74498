"""Every ```console block of README.md and docs/*.md runs and prints what it shows.

One test per block, named by file and line. The convention a block follows (its
environment tag, ``...`` wildcards, ``&`` background commands, port rewriting) is
in tests/doc_blocks.py's docstring. Also here: the README leads (under 250 lines,
a first ``epos-link read`` in its first 100, every docs/ page linked), and the
blocks that are skipped are only those a tag says need hardware or root, or are
run by another named test.
"""
from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
from pathlib import Path
from typing import Iterator

import pytest

from tests.doc_blocks import (BIN, DOCS, ENVIRONMENTS, ROOT, SKIP_REASONS, Background, Block,
                              all_blocks, environment, free_port, job_kill, localise, matches,
                              parse, rewrite_ports, run, workdir)

BLOCKS = all_blocks()
README = ROOT / "README.md"


@pytest.fixture(scope="module")
def bridge_sim(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[int, int]]:
    """``tcp-bridge serve --simulate`` (three axes) on the ports the docs call 1912 and 1913."""
    home = tmp_path_factory.mktemp("bridge-sim")
    nicos, maintenance = free_port(), free_port()
    job = Background(f"{BIN}/tcp-bridge serve --simulate --port {nicos} --maintenance-port "
                     f"{maintenance} --state-file {home}/state.json", workdir(home), environment(home))
    ready = job.ready_on(nicos)
    try:
        assert ready, "tcp-bridge serve --simulate did not start listening"
        yield {1912: nicos, 1913: maintenance}
    finally:
        job.stop()


@pytest.fixture(scope="module")
def sim_tcp(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[int, int]]:
    """``epos-link sim --tcp 127.0.0.1:4001 --drives 2,3``, on a free port the docs call 4001.

    With ``--gateway-timeout 20`` (ms): docs/epos-link.md's ``scan`` of all 127 nodes pays
    the gateway's timeout for each of the 124 absent ones, 37 s at the default 300 ms and
    2.5 s at 20 ms; what it prints is the same (an absent node is answered 0x05040000
    whenever that comes, and nodes 2 and 3 are given 5 s whatever the option says:
    epos_link/simulator/gateway.py). tests/test_cli_scan.py scans at the default."""
    home = tmp_path_factory.mktemp("sim-tcp")
    port = free_port()
    job = Background(f"{BIN}/epos-link sim --tcp 127.0.0.1:{port} --drives 2,3 --gateway-timeout 20",
                     workdir(home), environment(home))
    try:
        lines = job.first_lines([f"listening on socket://127.0.0.1:{port}"])
        assert lines and lines[0] == f"listening on socket://127.0.0.1:{port}", lines
        yield {4001: port}
    finally:
        job.stop()


@pytest.fixture
def given(block: Block, request: pytest.FixtureRequest) -> dict[int, int]:
    """The block's environment (skipped blocks start none): a fixture, so that starting a
    shared simulator or bridge shows in --durations as the setup of the first block that
    uses it, not as that block's own time (issue 32)."""
    if block.skip:
        pytest.skip(f"{block.id}: {block.skip}")
    for program in block.needs:
        if shutil.which(program) is None:
            pytest.skip(f"{block.id}: needs {program}, which is not installed here")
    if block.env == "bridge-sim":
        return dict(request.getfixturevalue("bridge_sim"))
    if block.env == "sim-tcp":
        return dict(request.getfixturevalue("sim_tcp"))
    return {}


@pytest.mark.parametrize("block", BLOCKS, ids=[b.id for b in BLOCKS])
def test_console_block(block: Block, given: dict[int, int], tmp_path: Path) -> None:
    cwd = workdir(tmp_path)
    links, status = set(os.listdir(cwd)), git_status()
    failures = run(block, rewrite_ports(block, given), cwd)
    assert not failures, "\n\n".join(failures)
    # The working directory stands for the reader's checkout (issue 34: the pages left
    # move.csv, cap.txt, drive2.dcf, ... in it): what a block writes goes to /tmp/.
    left = sorted(set(os.listdir(cwd)) - links)
    assert not left, f"{block.id} leaves {left} in the checkout: write them to /tmp/"
    left = sorted(git_status() - status)
    assert not left, f"{block.id} leaves {left} in the checkout (through a link)"


def git_status() -> set[str]:
    """The checkout's untracked files, as ``git status`` lists them (none outside git).
    Untracked only: a developer's edits while the block runs are not the block's."""
    done = subprocess.run(["git", "status", "--porcelain", "--untracked-files=all"], cwd=ROOT,
                          capture_output=True, text=True)
    lines = done.stdout.splitlines() if done.returncode == 0 else []
    return {line for line in lines if line.startswith("??")}


# --- the convention itself -----------------------------------------------------------


def test_every_block_names_a_known_environment() -> None:
    for b in BLOCKS:
        assert b.env in ENVIRONMENTS or b.skip is not None, f"{b.id}: doc-test: {b.env}"
        assert b.commands, f"{b.id}: a console block without a '$ ' command"


def test_skips_are_only_hardware_root_or_tested_elsewhere() -> None:
    """A skipped block must say why, from a short list; 'tested by' names a test that exists."""
    for b in BLOCKS:
        if b.skip is None:
            continue
        assert b.skip.startswith(SKIP_REASONS), f"{b.id}: skip: {b.skip}"
        if b.skip.startswith("tested by "):
            target = ROOT / b.skip.removeprefix("tested by ").split()[0].rstrip(",;:")
            assert target.is_file(), f"{b.id}: {target} does not exist"


def test_blocks_sharing_the_bridge_write_to_different_axes() -> None:
    """One bridge serves every bridge-sim block: an axis written by one must be theirs alone."""
    owner: dict[str, str] = {}
    for b in BLOCKS:
        if b.env != "bridge-sim":
            continue
        axes = {m.group(1) for c in b.commands for m in re.finditer(r"\b(\d+)S\d+", c.text)}
        for axis in axes:
            assert owner.setdefault(axis, b.id) == b.id, f"axis {axis}: {owner[axis]} and {b.id}"


def test_the_parser_reads_commands_outputs_and_tags(tmp_path: Path) -> None:
    doc = tmp_path / "x.md"
    doc.write_text("<!-- doc-test: sim-tcp, needs tshark -->\n```console\n"
                   "$ a \\\n  b\nout 1\n\n$ c << 'EOF'\nx\nEOF\n$ d &\nlistening\n```\n"
                   "```sh\n$ not run\n```\n  ```console\n  $ e\n  f\n  ```\n")
    one, two = parse(doc)
    assert (one.line, one.env, one.needs) == (2, "sim-tcp", ["tshark"])
    assert [(c.text, c.expected, c.background) for c in one.commands] == [
        ("a \\\n  b", ["out 1"], False), ("c << 'EOF'\nx\nEOF", [], False), ("d &", ["listening"], True)]
    assert (two.env, [(c.text, c.expected) for c in two.commands]) == ("none", [("e", ["f"])])


@pytest.mark.parametrize("expected, actual, ok", [
    (["a"], ["a"], True), (["a"], ["b"], False), (["a ... c"], ["a b c"], True),
    (["..."], [], True), (["a", "...", "z"], ["a", "b", "c", "z"], True),
    (["a", "..."], ["b"], False), ([], ["x"], False), (["x."], ["xy"], False),
])
def test_wildcards(expected: list[str], actual: list[str], ok: bool) -> None:
    assert matches(expected, actual) is ok


def test_a_wrong_output_fails_and_names_the_line(tmp_path: Path) -> None:
    doc = tmp_path / "x.md"
    doc.write_text("```console\n$ echo one\none\n$ echo $?; false\n0\n$ echo $?\n0\n```\n")
    (block,) = parse(doc)
    block.path = ROOT / "x.md"  # ids are relative to the repository
    failures = run(block, {}, workdir(tmp_path))
    assert len(failures) == 1 and failures[0].startswith("x.md:6: $ echo $?") and "\n1" in failures[0]


def test_kill_with_a_job_spec_signals_that_background_command(tmp_path: Path) -> None:
    """``kill [-SIG] %N`` acts on the block's Nth ``&`` command, as in an interactive shell
    (each command runs in a bash of its own, which has no jobs)."""
    doc = tmp_path / "x.md"
    doc.write_text("```console\n"
                   "$ sleep 60 &\n"
                   "$ bash -c 'trap \"echo TERM > got; exit 0\" TERM; echo ready; "
                   "while :; do sleep 0.1; done' &\nready\n"
                   "$ kill %2\n$ sleep 1\n$ cat got\nTERM\n"
                   "$ kill -9 %1\n$ echo $?\n0\n"
                   "$ kill -KILL %3\nbash: kill: %3: no such job\n$ echo $?\n1\n```\n")
    (block,) = parse(doc)
    block.path = ROOT / "x.md"
    assert run(block, {}, workdir(tmp_path)) == []
    assert job_kill("kill -9 %2") == (signal.SIGKILL, 2)
    assert job_kill("kill -SIGINT %1   # stop it") == (signal.SIGINT, 1)
    assert job_kill("kill %1") == (signal.SIGTERM, 1)
    assert job_kill("kill -NOSUCH %1") is None and job_kill("kill 1234") is None


def test_wait_for_a_job_and_tmp_is_the_tests_own(tmp_path: Path) -> None:
    """``wait %N`` waits for the Nth ``&`` command and gives its status; ``/tmp/`` is a
    scratch directory of the run's own, in commands and outputs alike."""
    doc = tmp_path / "x.md"
    doc.write_text("```console\n"
                   "$ sleep 1; echo done > /tmp/out.txt; exit 3 &\n"
                   "$ wait %1     # until it is done\n$ echo $?\n3\n"
                   "$ cat /tmp/out.txt; echo /tmp/out.txt\ndone\n/tmp/out.txt\n"
                   "$ wait %2\nbash: wait: %2: no such job\n```\n")
    (block,) = parse(doc)
    block.path = ROOT / "x.md"
    scratch = tmp_path / "scratch"
    (tmp_path / "cwd").mkdir()
    assert run(block, {}, workdir(tmp_path / "cwd"), scratch) == []
    assert (scratch / "out.txt").read_text() == "done\n"
    assert localise("a /tmp/x b=/tmp/y ./tmp/z ~/tmp/w", {}, scratch) == \
        f"a {scratch}/x b={scratch}/y ./tmp/z ~/tmp/w"


def test_a_bridge_s_port_options_are_rewritten_like_addresses(tmp_path: Path) -> None:
    doc = tmp_path / "x.md"
    doc.write_text("```console\n$ serve --port 1912 --maintenance-port -1 &\n"
                   "listening on 127.0.0.1:1912\n$ send 127.0.0.1:1912 --port=1913\n```\n")
    (block,) = parse(doc)
    ports = rewrite_ports(block, {})
    assert sorted(ports) == [1912, 1913] and 1912 not in ports.values()
    a, b = ports[1912], ports[1913]
    assert localise(block.commands[0].text, ports) == f"serve --port {a} --maintenance-port -1 &"
    assert localise(block.commands[0].expected[0], ports) == f"listening on 127.0.0.1:{a}"
    assert localise(block.commands[1].text, ports) == f"send 127.0.0.1:{a} --port={b}"


# --- the README leads --------------------------------------------------------------


def test_the_readme_is_short() -> None:
    assert len(README.read_text().split("\n")) < 250


def test_the_first_epos_link_read_is_near_the_top() -> None:
    lines = README.read_text().split("\n")
    first = next(i for i, line in enumerate(lines, 1) if re.search(r"epos-link read\b", line))
    assert first <= 100, first
    assert any(b.path == README and b.line < first for b in BLOCKS)  # and it is a tested block


def test_the_readme_links_every_docs_page() -> None:
    text = README.read_text()
    for page in DOCS[1:]:
        assert f"](docs/{page.name})" in text, page.name


def test_the_readme_keeps_the_two_set_up_commands() -> None:
    text = README.read_text()
    assert "python3 dev.py start" in text and "python3 dev.py test" in text


def test_no_link_points_at_a_missing_page_or_readme_section() -> None:
    for doc in DOCS:
        for target in re.findall(r"\]\(([^)#:]+\.md)(#[^)]*)?\)", doc.read_text()):
            assert (doc.parent / target[0]).resolve().is_file(), f"{doc.name}: {target[0]}"
    stale = subprocess.run(["grep", "-rn", "--include=*.py", "README" + "'s", "epos_link", "tcp_bridge",
                            "tests", "bench", "examples"], cwd=ROOT, capture_output=True, text=True)
    assert stale.stdout == "", stale.stdout
