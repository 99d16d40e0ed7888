"""Person detector, HMR engine, SMPL-X tail and their backends (onnxruntime, TensorRT, ground truth)."""
