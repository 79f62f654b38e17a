"""Real-robot inference: serve the latest policy to robots with a safety envelope (issue #16)."""
