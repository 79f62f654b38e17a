"""Pure evaluation math (numpy and stdlib only): episode stats, improvement timestep, eval history, curves."""
