"""Cost of taking one udp_multicast datagram off the bus as a checked frame (``runtime.frames.decode_datagram``:
msgpack, field types, identifier / DLC / data / flag checks) against python-can's own decoding in the same run
(``unpack_message(check=True)``, what its ``recv`` does per frame).

    python benchmarks/bench_frame_decode.py [--frames 200000]

Prints microseconds per frame and the ratio to python-can's decoding (the baseline of this run).
"""

from __future__ import annotations

import argparse
import time

import can
from can.interfaces.udp_multicast.utils import pack_message, unpack_message

from virtualaxis.runtime.frames import decode_datagram, frame_problem


def _per_frame_us(fn, items, repeat: int = 5) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        for item in items:
            fn(item)
        best = min(best, time.perf_counter() - t0)
    return best / len(items) * 1e6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=200_000)
    args = ap.parse_args()
    frames = [can.Message(arbitration_id=0x180 + (i % 64), is_extended_id=False, data=bytes([i & 0xFF] * (i % 9)),
                          channel="va-1-1") for i in range(args.frames)]
    datagrams = [pack_message(m) for m in frames]
    base = _per_frame_us(lambda d: unpack_message(d, replace={"timestamp": 1.0}, check=True), datagrams)
    ours = _per_frame_us(lambda d: decode_datagram(d, 1.0), datagrams)
    check = _per_frame_us(frame_problem, frames)

    print(f"{args.frames} frames, best of 5")
    print(f"python-can unpack_message(check=True): {base:.3f} us/frame (baseline)")
    print(f"decode_datagram:                       {ours:.3f} us/frame ({ours / base:.2f} x baseline)")
    print(f"frame_problem alone:                   {check:.3f} us/frame ({check / base:.2f} x baseline)")


if __name__ == "__main__":
    main()
