"""Pure learner math: groups, equivariant layers, networks, losses, replay. No transport, storage or metrics."""
