"""Stand-ins for licensed files (simulator, tests): procedural SMPL-X-layout body, contract ONNX models."""
