"""Shared fixtures for the integration tests that start ROS 2 processes."""
from __future__ import annotations

import fcntl
import os
import pathlib

import pytest

REPO_ROOT = pathlib.Path(__file__).resolve().parents[1]
_domain_lock = None


def _claim_ros_domain() -> int:
    """Hold a lock on a free ROS_DOMAIN_ID for this pytest process, so parallel runs on one
    machine never hear each other (DDS discovery is per domain)."""
    global _domain_lock
    lock_dir = pathlib.Path(os.environ.get("TMPDIR", "/tmp")) / "leapnbv-ros-domains"
    lock_dir.mkdir(parents=True, exist_ok=True)
    start = os.getpid() % 90
    for i in range(90):
        domain = 1 + (start + i) % 90
        handle = open(lock_dir / f"{domain}.lock", "w")
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            handle.close()
            continue
        _domain_lock = handle
        return domain
    raise RuntimeError(f"no free ROS_DOMAIN_ID lock in {lock_dir}")


def pytest_configure(config):
    # scripts/test already claims one for the whole run; a bare `pytest` claims its own.
    if "LEAPNBV_ROS_DOMAIN_CLAIMED" not in os.environ:
        os.environ["ROS_DOMAIN_ID"] = str(_claim_ros_domain())
        os.environ["LEAPNBV_ROS_DOMAIN_CLAIMED"] = "1"
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    os.environ.setdefault(
        "FASTRTPS_DEFAULT_PROFILES_FILE",
        str(REPO_ROOT / "src/leapnbv_bringup/config/fastdds_large_messages.xml"),
    )


@pytest.fixture(scope="session")
def repo_root() -> pathlib.Path:
    return REPO_ROOT
