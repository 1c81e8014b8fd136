"""Whole-recording time of `trmd deblur` on an idle machine and beside CPU-bound processes.

    python bench/bench_load.py [RECORDING] [--competitors 1] [--policies PASSIVE ACTIVE ""]
                               [-- extra trmd deblur flags]

For each OpenMP wait policy (``""``: the OpenMP runtime's own default, as before trmd chose one),
runs ``trmd deblur RECORDING`` once with no competitor and once with ``--competitors`` busy
loops started first, and prints the wall times and the slowdown. Users' machines are rarely idle:
the slowdown beside one competitor on a 2-core machine should stay well under 2× (half the
machine is gone; the work should not lose more).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
BUSY = "while True: pass"


def run_once(recording: Path, policy: str | None, extra: list[str], competitors: int) -> float:
    env = dict(os.environ)
    env.pop("OMP_WAIT_POLICY", None)
    if policy is not None:
        env["OMP_WAIT_POLICY"] = policy  # "" is not a policy: the runtime keeps its default
    busy = [subprocess.Popen([sys.executable, "-c", BUSY]) for _ in range(competitors)]
    try:
        time.sleep(0.5 if busy else 0.0)
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            subprocess.run([sys.executable, "-m", "trmd_cli", "deblur", str(recording), "-o",
                            str(Path(tmp) / "out"), *extra], env=env, check=True,
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            return time.perf_counter() - t0
    finally:
        for p in busy:
            p.kill()
            p.wait()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("recording", nargs="?", type=Path, default=SHARED / "recordings" /
                    "davis346.aedat4")
    ap.add_argument("--competitors", type=int, default=1)
    ap.add_argument("--policies", nargs="*", default=[None, ""],
                    help="OpenMP wait policies to compare (default: trmd's choice, and the "
                         "runtime's default)")
    args, extra = ap.parse_known_args()
    extra = [a for a in extra if a != "--"]
    print(f"{args.recording.name}, {os.cpu_count()} CPUs, `trmd deblur {' '.join(extra)}`")
    print(f"{'OpenMP wait policy':28s} {'idle s':>8s} {f'{args.competitors} busy s':>9s} "
          f"{'slowdown':>9s}")
    for policy in args.policies:
        idle = run_once(args.recording, policy, extra, 0)
        busy = run_once(args.recording, policy, extra, args.competitors)
        name = "trmd's (PASSIVE)" if policy is None else (policy or "runtime default")
        print(f"{name:28s} {idle:8.1f} {busy:9.1f} {busy / idle:8.2f}×", flush=True)


if __name__ == "__main__":
    main()
