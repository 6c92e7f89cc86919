"""Benchmark helpers: throughput timing, Brax's PPO on our env, device scaling."""
