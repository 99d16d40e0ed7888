"""Person detector, HMR engine, SMPL-X tail and their engine backends (onnxruntime, TensorRT, ground truth)."""
