"""Per-step cost of the online and batch StreamingEDMD at growing history lengths.

For each history length (number of snapshot pairs already observed) an estimator is
pre-filled by feeding a stream, then a block of ``observe`` + ``predict`` steps is timed.
The online estimator should cost the same at every length (target: within 1.5x between
200 and 20,000 pairs) and beat the batch pseudoinverse by at least 50x at 20,000 pairs.
If the PyPI package ``odmd`` (online DMD by rank-one updates) or a ``river`` with
``river.decomposition.OnlineDMD`` is installed, the same lifted pairs are run through it
for reference (one update and one prediction ``A y`` per step).

Timing blocks of all lengths and contenders are interleaved in a new random order in each
of several rounds, each block from a fresh copy of the pre-filled state after a short
untimed warm-up, and the fastest round is kept: on a shared machine this is the figure
least disturbed by other load.

Run from the repository root::

    python bench/bench_estimators.py [--steps 300] [--rounds 7] [--seed 0]
"""

from __future__ import annotations

import argparse
import copy
import gc
import importlib
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agents.estimators import StreamingEDMD, delay_embed  # noqa: E402

HISTORY_LENGTHS = (200, 2_000, 20_000)
CASES = {"lifted dim 2": {"delays": 0}, "lifted dim 6 (delays=2)": {"delays": 2},
         # Forgetting without ridge: the online estimator also keeps its QR summary of the
         # pairs each step, to refit from if P winds up (see StreamingEDMD's notes).
         "lifted dim 2, forget 0.9 (wind-up guard)": {"delays": 0, "forget": 0.9}}
FLATNESS_TARGET = 1.5
SPEEDUP_TARGET = 50.0
WARM_UP = 50  # untimed steps before each timed block

Step = Callable[[int], None]


def make_stream(n_samples: int, seed: int) -> np.ndarray:
    """A bounded, persistently exciting nonlinear 2-D stream, shape ``(n_samples, 2)``."""
    rng = np.random.default_rng(seed)
    A = np.array([[0.9, -0.3], [0.3, 0.9]])
    noise = 0.2 * rng.normal(size=(n_samples, 2))
    out = np.empty((n_samples, 2))
    z = rng.normal(size=2)
    for i in range(n_samples):
        out[i] = z
        z = A @ z + 0.4 * np.tanh(z[::-1] ** 2) + noise[i]
    return out


def _estimator_steps(
    online: bool, options: dict, stream: np.ndarray, length: int
) -> Callable[[], Step]:
    """Factory of timed steps: ``observe`` + ``predict`` after `length` pairs."""
    prefill = length + options["delays"] + 1  # samples giving `length` pairs
    est = StreamingEDMD(online=online, **options)
    for z in stream[:prefill]:
        est.observe(z)
    if est.n_pairs != length:
        raise RuntimeError(f"pre-fill gave {est.n_pairs} pairs, not {length}")
    upcoming = stream[prefill:]

    def fresh() -> Step:
        current = copy.deepcopy(est)

        def step(i: int) -> None:
            current.observe(upcoming[i])
            current.predict()

        return step

    return fresh


def _odmd_model(pairs_x: np.ndarray, pairs_y: np.ndarray) -> object | None:
    """``odmd.OnlineDMD`` initialised on the given pairs, or None if not installed."""
    try:
        odmd = importlib.import_module("odmd")
    except ImportError:
        return None
    model = odmd.OnlineDMD(pairs_x.shape[1], weighting=1.0)
    model.initialize(pairs_x.T, pairs_y.T)
    return model


def _river_model(pairs_x: np.ndarray, pairs_y: np.ndarray) -> object | None:
    """``river.decomposition.OnlineDMD`` fed the given pairs, or None if not installed."""
    try:
        decomposition = importlib.import_module("river.decomposition")
    except ImportError:
        return None
    if not hasattr(decomposition, "OnlineDMD"):
        return None
    model = decomposition.OnlineDMD(w=1.0, initialize=pairs_x.shape[1])
    for x, y in zip(pairs_x, pairs_y, strict=True):
        model.learn_one(x, y)
    return model


# Reference online-DMD packages: a builder of a model pre-filled with pairs (None when the
# package is missing) and the name of its one-pair update method. Both packages expose the
# fitted matrix as ``A``.
REFERENCES: dict[str, tuple[Callable[[np.ndarray, np.ndarray], object | None], str]] = {
    "odmd": (_odmd_model, "update"),
    "river": (_river_model, "learn_one"),
}


def _reference_steps(
    name: str, pairs_x: np.ndarray, pairs_y: np.ndarray, length: int
) -> Callable[[], Step] | None:
    """Factory of timed steps (update + prediction) of package `name`, None if absent."""
    build, update_name = REFERENCES[name]
    model = build(pairs_x[:length], pairs_y[:length])
    if model is None:
        return None

    def fresh() -> Step:
        current = copy.deepcopy(model)
        update = getattr(current, update_name)

        def step(i: int) -> None:
            update(pairs_x[length + i], pairs_y[length + i])
            current.A @ pairs_y[length + i]

        return step

    return fresh


def _time_block(step: Step, n_steps: int) -> float:
    """Mean µs per call of ``step(i)`` for the last `n_steps` of ``WARM_UP + n_steps``.

    The untimed warm-up lets caches and the BLAS worker threads left spinning by the
    previous block settle; the garbage collector is off while timing.
    """
    for i in range(WARM_UP):
        step(i)
    gc.disable()
    try:
        start = time.perf_counter()
        for i in range(WARM_UP, WARM_UP + n_steps):
            step(i)
        elapsed = time.perf_counter() - start
    finally:
        gc.enable()
    return elapsed / n_steps * 1e6


def run(
    lengths: tuple[int, ...] = HISTORY_LENGTHS,
    n_steps: int = 300,
    rounds: int = 7,
    seed: int = 0,
) -> dict:
    """Time the online and batch estimators (and installed reference packages).

    Returns
    -------
    dict
        ``{case: {"online_us": {length: µs per step}, "batch_us": {...},
        "reference_us": {package: {length: µs} or None},
        "online_flatness": online at the longest / online at the shortest history,
        "batch_over_online": batch / online at the longest history,
        "reference_over_online": {package: ratio at the longest history or None}}}``.
    """
    longest, shortest = max(lengths), min(lengths)
    figures: dict = {}
    for case, options in CASES.items():
        stream = make_stream(longest + options["delays"] + 1 + WARM_UP + n_steps, seed)
        psi = delay_embed(stream, options["delays"])
        pairs_x, pairs_y = psi[:-1], psi[1:]
        contenders: dict[tuple[str, int], Callable[[], Step]] = {}
        for length in lengths:
            contenders["online", length] = _estimator_steps(True, options, stream, length)
            contenders["batch", length] = _estimator_steps(False, options, stream, length)
            for name in REFERENCES:
                steps = _reference_steps(name, pairs_x, pairs_y, length)
                if steps is not None:
                    contenders[name, length] = steps
        best = {key: np.inf for key in contenders}
        keys = list(contenders)
        order = np.random.default_rng(seed)
        for _ in range(rounds):
            # A new order each round, so that no contender always follows a heavy one.
            for index in order.permutation(len(keys)):
                key = keys[index]
                best[key] = min(best[key], _time_block(contenders[key](), n_steps))
        online_us = {length: best["online", length] for length in lengths}
        batch_us = {length: best["batch", length] for length in lengths}
        reference_us = {
            name: {length: best[name, length] for length in lengths}
            if (name, longest) in best
            else None
            for name in REFERENCES
        }
        figures[case] = {
            "online_us": online_us,
            "batch_us": batch_us,
            "reference_us": reference_us,
            "online_flatness": online_us[longest] / online_us[shortest],
            "batch_over_online": batch_us[longest] / online_us[longest],
            "reference_over_online": {
                name: None if timings is None else timings[longest] / online_us[longest]
                for name, timings in reference_us.items()
            },
        }
    return figures


def main(n_steps: int, rounds: int, seed: int) -> None:
    figures = run(n_steps=n_steps, rounds=rounds, seed=seed)
    longest, shortest = max(HISTORY_LENGTHS), min(HISTORY_LENGTHS)
    print(f"StreamingEDMD: µs per observe+predict step ({n_steps} steps, best of {rounds})")
    for case, result in figures.items():
        present = [name for name, t in result["reference_us"].items() if t is not None]
        print(f"\n{case}")
        header = f"  {'pairs':>8}  {'online':>10}  {'batch':>10}"
        print(header + "".join(f"  {name:>10}" for name in present))
        for length in HISTORY_LENGTHS:
            row = f"  {length:>8,}  {result['online_us'][length]:>10.1f}"
            row += f"  {result['batch_us'][length]:>10.1f}"
            row += "".join(f"  {result['reference_us'][n][length]:>10.1f}" for n in present)
            print(row)
        flat, speedup = result["online_flatness"], result["batch_over_online"]
        verdict = "ok" if flat <= FLATNESS_TARGET else "MISSED"
        print(
            f"  online flatness {longest:,} vs {shortest:,} pairs: {flat:.2f}x "
            f"({verdict}, target <= {FLATNESS_TARGET}x)"
        )
        verdict = "ok" if speedup >= SPEEDUP_TARGET else "MISSED"
        print(
            f"  batch / online at {longest:,} pairs: {speedup:.0f}x "
            f"({verdict}, target >= {SPEEDUP_TARGET:.0f}x)"
        )
        for name, ratio in result["reference_over_online"].items():
            if ratio is None:
                print(f"  {name}: online DMD unavailable (not installed), skipped")
            else:
                print(
                    f"  {name} / online at {longest:,} pairs: {ratio:.2f}x per step "
                    f"({name} gets the lifted pairs: no lifting, no input checks)"
                )


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=300, help="timed steps per block")
    parser.add_argument("--rounds", type=int, default=7, help="timing rounds (best kept)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the stream")
    args = parser.parse_args()
    main(args.steps, args.rounds, args.seed)
