"""Evaluator service: deterministic rollouts of broadcast weights on held-out seeds, and learning curves."""
