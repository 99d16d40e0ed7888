"""rosbag2 (MCAP storage) writing, reading and checking with rosbags, without ROS installed.

The bag I/O in one import: every name of the modules it is made of, one per concern:

- :mod:`leapnbv_bags.writer`: BagWriter and the QoS profiles it records;
- :mod:`leapnbv_bags.reader`: read_bag (a bag without its MCAP summary included);
- :mod:`leapnbv_bags.check`: check_bag, validate_bag_crcs (what the bag tools run first);
- :mod:`leapnbv_bags.typestore`: the message types (Jazzy's and leapnbv_msgs');
- :mod:`leapnbv_bags.cli`: ``python -m leapnbv_bags.bag_io BAG``;
- :mod:`leapnbv_bags.errors`: BagError.

The bag tools' exit codes are :class:`leapnbv_common.exit_codes.BagToolExit`; ``EXIT_*`` here are its members.
"""

from __future__ import annotations

from leapnbv_bags.check import METADATA_FILE, BagCheck, McapFileCheck, check_bag, validate_bag_crcs
from leapnbv_bags.cli import main
from leapnbv_bags.errors import BagError
from leapnbv_bags.reader import read_bag
from leapnbv_bags.typestore import find_leapnbv_msg_dir, load_leapnbv_msg_definitions, make_typestore
from leapnbv_bags.writer import (
    BAG_VERSION,
    RELIABLE_QOS,
    SENSOR_DATA_QOS,
    TRANSIENT_LOCAL_QOS,
    BagWriter,
    MessageOrBytes,
)
from leapnbv_common.exit_codes import BagToolExit

EXIT_OK = BagToolExit.OK
EXIT_OUTPUTS_CHANGED = BagToolExit.OUTPUTS_CHANGED
EXIT_USAGE = BagToolExit.USAGE
EXIT_UNREADABLE_BAG = BagToolExit.UNREADABLE_BAG

__all__ = [
    "BAG_VERSION",
    "EXIT_OK",
    "EXIT_OUTPUTS_CHANGED",
    "EXIT_UNREADABLE_BAG",
    "EXIT_USAGE",
    "METADATA_FILE",
    "RELIABLE_QOS",
    "SENSOR_DATA_QOS",
    "TRANSIENT_LOCAL_QOS",
    "BagCheck",
    "BagError",
    "BagToolExit",
    "BagWriter",
    "McapFileCheck",
    "MessageOrBytes",
    "check_bag",
    "find_leapnbv_msg_dir",
    "load_leapnbv_msg_definitions",
    "main",
    "make_typestore",
    "read_bag",
    "validate_bag_crcs",
]

if __name__ == "__main__":
    raise SystemExit(main())
