"""The learner: MAPPO's networks, normalization, losses, the jitted algorithm and its trainer
variants."""
