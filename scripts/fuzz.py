#!/usr/bin/env python
"""A longer fuzzing run of the deck parser and the Sun raster reader (minutes; not CI).

    python scripts/fuzz.py --minutes 2
    python scripts/fuzz.py --minutes 10 --targets deck-mutated raster-mutated --seed 7

It runs the properties of tests/test_fuzz.py (the same generators and the same checks:
a Deck or a `file:line:` DeckError, never another exception; an image or an ImageError,
fast, with bounded memory) round-robin, in batches, until the time is up, and reports
how many inputs each target tried, what the outcomes were, and every failure with the
smallest input hypothesis could shrink it to. Exit status 1 if anything failed.
"""

from __future__ import annotations

import argparse
import collections
import os
import random
import sys
import time
import traceback
import warnings

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, os.path.join(ROOT, "tests"))
sys.path.insert(0, ROOT)

from hypothesis import HealthCheck, Phase, given, seed, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

import test_fuzz as T  # noqa: E402  (the generators and checks, one source of truth)


def _raster_bytes(data: bytes) -> str:
    T.test_random_bytes_as_rasters.hypothesis.inner_test(data)
    return "checked"


def _outcome_name(result) -> str:
    if isinstance(result, str):
        return result
    return "image" if hasattr(result, "shape") else type(result).__name__


TARGETS = {
    # name: (strategy, check(input) -> outcome)
    "deck-tokens": (T.token_stream(), T.check_deck_text),
    "deck-mutated": (T.mutated_deck(), T.check_deck_text),
    "deck-text": (st.text(max_size=600), T.check_deck_text),
    "deck-valid": (T.valid_deck(), lambda case: T.test_valid_decks_parse_to_what_they_say_and_round_trip.hypothesis.inner_test(case) or "deck"),
    "raster-valid": (T.raster_file(), lambda data: T.test_well_formed_rasters_decode.hypothesis.inner_test(data) or "image"),
    "raster-mutated": (T.mutated_raster(), T.check_raster),
    "raster-bytes": (st.binary(max_size=4000), _raster_bytes),
    "raster-round-trip": (
        st.tuples(st.integers(1, 40), st.integers(1, 40), st.booleans(), st.integers(0, 2**32 - 1)),
        lambda args: T.test_small_and_odd_sizes_round_trip.hypothesis.inner_test(*args) or "round trip",
    ),
}


class Target:
    def __init__(self, name: str):
        self.name = name
        self.strategy, self.check = TARGETS[name]
        self.tried = 0
        self.outcomes: collections.Counter[str] = collections.Counter()
        self.failures: dict[str, list] = {}  # message → [times found, smallest failing input]
        self.last_failing = None

    def run_batch(self, examples: int, batch_seed: int) -> bool:
        """Run one batch; True when it found a failure not seen before."""
        @seed(batch_seed)
        @settings(
            max_examples=examples,
            deadline=None,
            database=None,
            phases=[Phase.generate, Phase.shrink],
            suppress_health_check=list(HealthCheck),
            report_multiple_bugs=False,
        )
        @given(self.strategy)
        def prop(value):
            self.tried += 1
            try:
                self.outcomes[_outcome_name(self.check(value))] += 1
            except BaseException:
                self.last_failing = value
                raise

        try:
            prop()
        except KeyboardInterrupt:
            raise
        except BaseException as e:  # a failure, shrunk: the last failing input is the smallest
            summary = "".join(traceback.format_exception_only(type(e), e)).strip().splitlines()
            where = traceback.extract_tb(e.__traceback__)[-1]
            message = f"{summary[0][:300]}  (at {os.path.basename(where.filename)}:{where.lineno})"
            example = repr(self.last_failing)[:2000]
            if message in self.failures:
                found = self.failures[message]
                found[0] += 1
                found[1] = min(found[1], example, key=len)
                return False
            self.failures[message] = [1, example]
            return True
        return False


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--minutes", type=float, default=2.0, help="how long to fuzz (default 2)")
    parser.add_argument("--targets", nargs="+", choices=sorted(TARGETS), default=list(TARGETS), help="what to fuzz (default: all)")
    parser.add_argument("--batch", type=int, default=300, help="inputs per target per round (default 300)")
    parser.add_argument("--seed", type=int, default=None, help="random seed (default: a fresh one, printed)")
    args = parser.parse_args(argv)

    master = args.seed if args.seed is not None else random.SystemRandom().randrange(2**32)
    rng = random.Random(master)
    targets = [Target(n) for n in args.targets]
    print(f"fuzzing {', '.join(args.targets)} for {args.minutes:g} min (seed {master})", flush=True)
    warnings.simplefilter("ignore")  # NumPy overflow warnings from hostile numbers are expected
    start = time.monotonic()
    end = start + 60 * args.minutes
    rounds, last_report = 0, start
    try:
        while time.monotonic() < end:
            for t in targets:
                if time.monotonic() >= end:
                    break
                if t.run_batch(args.batch, rng.randrange(2**32)):  # a failure not seen before
                    message, (_, example) = list(t.failures.items())[-1]
                    print(f"FAIL {t.name}: {message}\n     input: {example}", flush=True)
            rounds += 1
            if time.monotonic() - last_report >= 15:
                last_report = time.monotonic()
                print(f"  {last_report - start:6.0f} s  round {rounds}: {sum(t.tried for t in targets)} inputs", flush=True)
    except KeyboardInterrupt:
        print("interrupted", flush=True)

    elapsed = time.monotonic() - start
    total = sum(t.tried for t in targets)
    failures = sum(len(t.failures) for t in targets)
    print(f"\n{total} inputs in {elapsed:.0f} s ({total / max(elapsed, 1e-9):.0f}/s), {failures} distinct failure(s)")
    for t in targets:
        outcomes = ", ".join(f"{k} {v}" for k, v in t.outcomes.most_common())
        print(f"  {t.name:18s} {t.tried:8d} tried  {len(t.failures)} failing  ({outcomes})")
    for t in targets:
        for message, (times, example) in t.failures.items():
            print(f"\nFAIL {t.name} (found {times}x): {message}\n     smallest input: {example}")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
