"""Reinforcement learning on frozen embeddings: batched suite environments, observers, PPO, the expert
policy and the demonstrations recorded from it."""
