"""A managed stage node for the lifecycle tests: configure loads a model file, activate serves.

Run as a script (``python tests/lifecycle_test_node.py --ros-args ...``) or as a module with tests/ on the
path (``main()``: how the graph runner's standby process starts a node). Parameters: model_file_path
(configure fails while it is missing: FileNotFoundError naming it) and the ManagedNode ones
(autostart, configure_retry_period_s). While active, every std_msgs/String on ``model_stage_in`` is
answered on ``model_stage_out`` (a lifecycle publisher made in configure) with "<model text>:<input>".
"""
from __future__ import annotations

import os
from dataclasses import dataclass

from std_msgs.msg import String

from leapnbv_common.managed_node import ManagedNode
from leapnbv_common.node_params import run_node
from leapnbv_common.params import param
from leapnbv_common.qos import stage_input_qos, stage_output_qos

INPUT, OUTPUT = "model_stage_in", "model_stage_out"


@dataclass
class ModelStageParams:
    model_file_path: str = param("", "the model file configure loads")


class ModelStage(ManagedNode):
    def __init__(self) -> None:
        super().__init__("model_stage", ModelStageParams, hardware_id="test")
        self.model = None
        self.output = None

    def configure_stage(self) -> None:
        path = self.params.value.model_file_path
        self.output = self.create_lifecycle_publisher(String, OUTPUT, stage_output_qos())
        if not os.path.exists(path):
            raise FileNotFoundError(f"model file {path!r} not found")
        with open(path) as handle:
            self.model = handle.read().strip()

    def activate_stage(self) -> None:
        self.create_subscription(String, INPUT, self.on_input, stage_input_qos(10))

    def on_input(self, msg: String) -> None:
        self.diagnostics.frame_in()
        self.output.publish(String(data=f"{self.model}:{msg.data}"))

    def cleanup_stage(self) -> None:
        self.model = None


def main(args=None) -> None:
    run_node(ModelStage, args)


if __name__ == "__main__":
    main()
