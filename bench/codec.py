"""Codec speed against wire time: ``python bench/codec.py [--runs 7]``.

Encodes and decodes the guide's ReadObject request/answer pair (2.2.9) and
compares the codec's time with the time the same bytes take on an RS232 link
at 115200 baud 8N1 (10 bits per byte). Prints medians over several runs.
"""
from __future__ import annotations

import argparse
import statistics
import time

from epos_link.framing import NEED_DATA, FrameDecoder
from epos_link.messages import ReadObject, ReadObjectAnswer, decode_answer, decode_request

BAUD = 115200
BITS_PER_BYTE = 10  # start + 8 data + stop


def bench(n: int) -> dict[str, float]:
    req = ReadObject(1, 0x30B0, 0)
    ans = ReadObjectAnswer(0, bytes.fromhex("01 90 00 00"))
    wire_req, wire_ans = req.encode(), ans.encode()

    t0 = time.perf_counter()
    for _ in range(n):
        req.encode()
        ans.encode()
    t_encode = (time.perf_counter() - t0) / n

    dec_host, dec_dev = FrameDecoder(), FrameDecoder()
    t0 = time.perf_counter()
    for _ in range(n):
        dec_dev.feed(wire_req)
        frame = dec_dev.next_frame()
        decode_request(frame)  # type: ignore[arg-type]
        dec_host.feed(wire_ans)
        frame = dec_host.next_frame()
        decode_answer(frame, ReadObject)  # type: ignore[arg-type]
    t_decode = (time.perf_counter() - t0) / n
    assert dec_host.next_frame() is NEED_DATA
    wire = (len(wire_req) + len(wire_ans)) * BITS_PER_BYTE / BAUD
    return {"encode": t_encode, "decode": t_decode, "wire": wire}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("-n", type=int, default=20000, help="request/answer pairs per run")
    args = ap.parse_args()
    runs = [bench(args.n) for _ in range(args.runs)]
    enc = statistics.median(r["encode"] for r in runs)
    dec = statistics.median(r["decode"] for r in runs)
    wire = runs[0]["wire"]
    print(f"ReadObject request + answer, {args.runs} runs of {args.n} pairs, medians:")
    print(f"  encode both frames   {enc * 1e6:8.2f} us/pair  {1 / enc * 2:10.0f} frames/s")
    print(f"  decode both frames   {dec * 1e6:8.2f} us/pair  {1 / dec * 2:10.0f} frames/s")
    print(f"  wire time @115200    {wire * 1e6:8.2f} us/pair  (25 bytes, 8N1)")
    print(f"  codec / wire         {(enc + dec) / wire * 100:8.3f} %   (goal: under 1 %)")


if __name__ == "__main__":
    main()
