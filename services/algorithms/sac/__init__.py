"""Recurrent SAC (Equi-RSAC): hyperparameters (``config``), losses (``losses``), the update
(``agent``), the config the learner runs (``algorithm``) and the policy consumers run (``policy``)."""
