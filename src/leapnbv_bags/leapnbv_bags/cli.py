"""``python -m leapnbv_bags.bag_io BAG``: check a bag and print its topics and message counts."""

from __future__ import annotations

import argparse
import sys
from typing import Dict, Optional, Sequence

from leapnbv_bags.check import check_bag
from leapnbv_bags.errors import BagError
from leapnbv_bags.reader import read_bag
from leapnbv_common.exit_codes import BagToolExit

__all__ = ["main"]


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Check the bag named on the command line and print its topics and message counts.

    Args:
        argv: the arguments (``sys.argv[1:]`` if None).

    Returns:
        BagToolExit.OK, or UNREADABLE_BAG with one line on stderr naming the path and what is wrong
        (a usage error exits with USAGE from argparse).
    """
    parser = argparse.ArgumentParser(
        prog="python -m leapnbv_bags.bag_io",
        description="Check a rosbag2 bag (metadata.yaml, every MCAP chunk's CRC) and print its topics. "
                    f"Exit codes: {BagToolExit.OK} readable, {BagToolExit.USAGE} usage, "
                    f"{BagToolExit.UNREADABLE_BAG} unreadable bag (one line: the path and what is wrong).")
    parser.add_argument("bag", help="rosbag2 directory")
    args = parser.parse_args(argv)
    try:
        check = check_bag(args.bag)
        counts: Dict[str, int] = {}
        for topic, msgtype, _, _ in read_bag(args.bag, raw=True):
            counts[f"{topic} ({msgtype})"] = counts.get(f"{topic} ({msgtype})", 0) + 1
    except BagError as error:
        print(f"[bag] unreadable bag: {error}", file=sys.stderr)
        return BagToolExit.UNREADABLE_BAG
    print(f"[bag] {args.bag}: {check.storage}, {len(check.files)} file(s), {sum(counts.values())} messages")
    for name, count in sorted(counts.items()):
        print(f"  {count:6d}  {name}")
    return BagToolExit.OK
