"""Augmenter service: multi-group equivariant augmentation of episodes (MEA)."""
