"""Train the bipedal task (2 leg agents; arms held by PD): ``python -m experiments.bipedal``."""

from experiments.train_task import main

if __name__ == "__main__":
  main("bipedal")
