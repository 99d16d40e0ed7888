"""Print the committed seeds of every benchmark family (FAMILY_SEEDS of leapnbv_evaluation.benchmark_set).

For each family of FAMILY_CHANGES: the first ``--count`` seeds from 0 whose scene generates and shows
the person (``select_benchmark_seeds`` under the family's config, small stand-in body).
Usage: scripts/env.sh python scripts/experiments/family_seeds.py [--count 40] [--families corner,corridor]
Prints a Python dict literal. Exit 0; 2 on an unknown family.
"""
from __future__ import annotations

import argparse
import sys

from leapnbv_evaluation.benchmark_set import FAMILY_CHANGES, benchmark_config, select_benchmark_seeds
from leapnbv_perception.smplx_layer import SMPLXModel
from leapnbv_stand_ins.files import ensure_stand_in_body_model


def main(argv) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--count", type=int, default=40)
    parser.add_argument("--families", default=",".join(FAMILY_CHANGES))
    args = parser.parse_args(argv)
    families = [f for f in args.families.split(",") if f]
    if any(f not in FAMILY_CHANGES for f in families):
        print(f"family_seeds: unknown family in {families}; known: {list(FAMILY_CHANGES)}", file=sys.stderr)
        return 2
    body = SMPLXModel.load(ensure_stand_in_body_model("small"))
    print("FAMILY_SEEDS: Dict[str, List[int]] = {")
    for family in families:
        seeds = select_benchmark_seeds(args.count, body, benchmark_config(0, family), max_seed=100 * args.count)
        print(f"    {family!r}: {seeds},")
        sys.stdout.flush()
    print("}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
