"""MASH-JAX: one agent per limb of a single humanoid, trained with MAPPO over MuJoCo MJX."""

__version__ = "0.1.0"
