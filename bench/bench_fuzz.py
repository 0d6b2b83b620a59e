"""Long run of the fuzz and fault suite (ground/testing); prints a table of counts per campaign.

Campaigns: NSP traffic (random and damaged frames, PING after each burst; on a pty, and paced
on TCP), client against
misbehaving ports (pty and socket://, garbage / slow / silent / flooding), transfer faults on a
device holding a catalog, damaged state directories (in process and as processes), TCP link
policy (takeover, a takeover while a late reply is pending, silent, cut, chattering clients, idle
timeout, connection flood), SIGKILL during a catalog commit, and attitude-feed faults (malformed,
nested, huge, future and past samples, floods, silent and dropping peers) with the time from each
fault to the next OK solve. ``--messages`` scales every campaign; the seed makes a run repeatable.
Every count but messages and faults should be 0; the exit status is 1 otherwise.

Usage: .venv/bin/python bench/bench_fuzz.py [--messages 20000] [--seed 1] [--only nsp,tcp,...]
"""

from __future__ import annotations

import argparse
import sys
import time

from ground.testing import commit_kill, feed_faults, nsp_fuzz, port_faults, state_faults, tcp_faults, upload_faults
from ground.testing.tally import Tally, table


def campaigns(n: int, seed: int) -> dict:
    """name -> callable returning a Tally, sized so the run sends about ``n`` messages."""
    return {
        "nsp": lambda: nsp_fuzz.run(seed, bursts=max(10, n // 25))[0],
        "nsp_paced_tcp": lambda: nsp_fuzz.run(
            seed + 1, bursts=max(10, n // 100), device_args=("--tcp", "127.0.0.1:0", "--pace", "--baud", "921600")
        )[0],
        "client_ports": lambda: (
            port_faults.run(seed, trials=max(9, n // 200), timeout=0.2)
            .add(port_faults.run(seed + 1, trials=max(9, n // 200), timeout=0.2, tcp=True))
            .add(port_faults.run_flood(seed, calls=5, tcp=True))
            .add(port_faults.run_flood(seed, calls=5, tcp=False))
        ),
        "upload": lambda: upload_faults.run(seed, scenarios=max(11, n // 400), restarts=max(1, n // 5000)),
        "state": lambda: state_faults.run(seed, trials=max(17, n // 50), process=False).add(
            state_faults.run(seed + 1, trials=max(3, n // 2000), process=True)
        ),
        "tcp": lambda: tcp_faults.run(seed, rounds=max(5, n // 500), connections=200),
        "commit_kill": lambda: commit_kill.run(seed, kills=max(3, n // 2000))[0],
        "feed": lambda: feed_faults.run(seed, rounds=max(12, n // 500)),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--messages", type=int, default=20000, help="scale: about this many messages in all")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--only", help="comma-separated campaigns to run (default: all)")
    args = ap.parse_args()
    if args.messages < 1:
        ap.error("--messages must be >= 1")
    todo = campaigns(args.messages, args.seed)
    if args.only:
        unknown = set(args.only.split(",")) - set(todo)
        if unknown:
            ap.error(f"unknown campaign(s) {sorted(unknown)}; choose from {sorted(todo)}")
        todo = {k: v for k, v in todo.items() if k in args.only.split(",")}
    rows: dict[str, Tally] = {}
    for name, run in todo.items():
        t0 = time.monotonic()
        rows[name] = run()
        print(f"{name}: {time.monotonic() - t0:.1f} s", file=sys.stderr, flush=True)
    print(f"bench_fuzz --messages {args.messages} --seed {args.seed}")
    print(table(rows))
    for name, tally in rows.items():
        for note in tally.notes:
            print(f"  {name}: {note}")
    return 1 if any(t.failures for t in rows.values()) else 0


if __name__ == "__main__":
    sys.exit(main())
