#!/usr/bin/env python3
"""fdatasync latency of the log's two possible write patterns, on this disk.

The write-ahead log appends each group commit to its segment and syncs it
(`fdatasync`). Appending grows the file, so each sync must also write the
file's inode; overwriting a segment that was filled with zeros beforehand
does not. This measures both (and `posix_fallocate`, which reserves blocks
without writing them), interleaved, in the directory given (default: the
current one), with frames of a typical group commit's size.

    python3 benches/fsync_latency.py [DIR] [--frames N] [--bytes B] [--rounds R]

Used by BENCHMARKS.md section 8 ("The log's sync on this disk").
"""

import argparse
import os
import statistics
import time


def run(directory: str, mode: str, frames: int, size: int) -> list[float]:
    path = os.path.join(directory, f".fsync-latency-{mode}-{os.getpid()}")
    fd = os.open(path, os.O_CREAT | os.O_WRONLY | os.O_TRUNC, 0o600)
    try:
        total = frames * size
        if mode == "zeroed":
            chunk = b"\0" * (1 << 20)
            for _ in range(0, total, len(chunk)):
                os.write(fd, chunk)
            os.fsync(fd)
            os.lseek(fd, 0, os.SEEK_SET)
        elif mode == "fallocate":
            os.posix_fallocate(fd, 0, total)
            os.fsync(fd)
        frame = os.urandom(size)
        out = []
        for _ in range(frames):
            t = time.perf_counter()
            os.write(fd, frame)
            os.fdatasync(fd)
            out.append(time.perf_counter() - t)
        return out
    finally:
        os.close(fd)
        os.unlink(path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dir", nargs="?", default=".")
    ap.add_argument("--frames", type=int, default=2000, help="syncs per run")
    ap.add_argument("--bytes", type=int, default=8192, help="bytes per frame")
    ap.add_argument("--rounds", type=int, default=3, help="interleaved rounds")
    a = ap.parse_args()
    modes = ["append", "zeroed", "fallocate"]
    print(f"fdatasync after each {a.bytes}-byte write, {a.frames} per run, in {os.path.abspath(a.dir)}\n")
    print("| round | pattern | mean | p50 | p99 | max |")
    print("|---|---|---|---|---|---|")
    for r in range(1, a.rounds + 1):
        for mode in modes:
            lat = sorted(run(a.dir, mode, a.frames, a.bytes))
            ms = lambda x: f"{x * 1e3:.3f} ms"  # noqa: E731
            print(
                f"| {r} | {mode} | {ms(statistics.fmean(lat))} | {ms(lat[len(lat) // 2])} "
                f"| {ms(lat[int(len(lat) * 0.99)])} | {ms(lat[-1])} |"
            )


if __name__ == "__main__":
    main()
