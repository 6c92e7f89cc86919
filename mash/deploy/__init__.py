"""A trained policy outside training: policy folders, ONNX export, native MuJoCo (sim-to-sim)."""
