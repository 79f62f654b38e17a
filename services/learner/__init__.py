"""Learner: Equi-RSAC (recurrent SAC, C4/D4-equivariant) trained from sequence replay."""
