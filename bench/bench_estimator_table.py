"""Mean required sensing range of stay, persist, the paper's EDMD-b and auto, per surface.

``python bench/bench_estimator_table.py`` prints, for follower 1 at the paper's settings
(T_c = 1.28, d = 3.57, 4 + 36 ticks), the table on the three paper surfaces and on the held-out
``gaussian-hill`` and ``ripple`` (never used to choose auto's candidates), the ratio
auto / EDMD-b (target <= 0.25 on the paper surfaces), and auto / persist over the comm periods
0.32 ... 5.12 (target <= 1). Runs use the in-memory layout, whose numbers a test shows to be
identical to the Zenoh layouts.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from protocol.config import RunConfig  # noqa: E402
from swarm.local import run_local  # noqa: E402

PAPER = ("elliptic", "hyperbolic", "wavy")
HELD_OUT = ("gaussian-hill", "ripple")
ESTIMATORS = {"stay": {"estimator": "stay"}, "persist": {"estimator": "persist"},
              "edmd-b": {"estimator": "edmd", "dictionary": "b"}, "auto": {"estimator": "auto"}}
COMM_PERIODS = (0.32, 0.64, 1.28, 2.56, 5.12)


def required(surface: str, comm_period: float, **options) -> float:
    summary, _ = run_local(RunConfig(surface=surface, comm_period=comm_period, **options))
    return summary["followers"]["1"]["mean_required_range"]


def table() -> dict:
    out = {}
    for surface in PAPER + HELD_OUT:
        out[surface] = {name: required(surface, 1.28, **opts) for name, opts in ESTIMATORS.items()}
    return out


def comm_period_sweep(surfaces=PAPER + HELD_OUT) -> dict:
    return {(s, tc): {name: required(s, tc, **ESTIMATORS[name]) for name in ("persist", "edmd-b", "auto")}
            for s in surfaces for tc in COMM_PERIODS}


def main() -> None:
    argparse.ArgumentParser(description=__doc__).parse_args()
    print("mean required sensing range, follower 1, T_c = 1.28")
    print(f"{'surface':<15}{'stay':>10}{'persist':>10}{'edmd-b':>10}{'auto':>10}{'auto/edmd-b':>13}")
    for surface, row in table().items():
        tag = "" if surface in PAPER else "  (held out)"
        print(f"{surface:<15}{row['stay']:>10.4f}{row['persist']:>10.4f}{row['edmd-b']:>10.5f}"
              f"{row['auto']:>10.5f}{row['auto'] / row['edmd-b']:>13.3f}{tag}")
    print("\nauto / persist by comm period (target <= 1), auto / edmd-b in brackets")
    sweep = comm_period_sweep()
    print(f"{'surface':<15}" + "".join(f"{tc:>14}" for tc in COMM_PERIODS))
    for surface in PAPER + HELD_OUT:
        cells = []
        for tc in COMM_PERIODS:
            r = sweep[(surface, tc)]
            cells.append(f"{r['auto'] / r['persist']:>6.3f} ({r['auto'] / r['edmd-b']:.2f})")
        print(f"{surface:<15}" + "".join(f"{c:>14}" for c in cells))


if __name__ == "__main__":
    main()
