"""Model tools (not installed on the robot): the SMPLer-X network in PyTorch, its checkpoints
and the ONNX export. Runs in the tools environment (tools/setup_tools_env.sh)."""
