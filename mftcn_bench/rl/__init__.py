"""Reinforcement learning on frozen embeddings: batched suite environments, observers and PPO."""
