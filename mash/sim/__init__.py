"""The simulated robot and its task: robot files, the MJX model, layout, env, rewards,
randomization."""
