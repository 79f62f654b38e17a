"""GASv2: a DreamerV2 world model with the hybrid controller (paper Sec. IV-C; reference sections 5
and 6), in plain PyTorch. Pure modules: no transport, metrics or processes."""
