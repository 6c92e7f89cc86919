"""Training runs on disk: experiment configs and presets, the host loop and its hooks, checkpoints,
loggers."""
