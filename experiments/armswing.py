"""Train the arm-swing task (2 leg + 2 arm agents): ``python -m experiments.armswing``."""

from experiments.train_task import main

if __name__ == "__main__":
  main("armswing")
