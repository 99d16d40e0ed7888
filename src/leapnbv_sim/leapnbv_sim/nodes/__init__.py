"""ROS 2 nodes of the simulator (the closed-loop camera)."""
from __future__ import annotations
