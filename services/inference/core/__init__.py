"""Pure parts of the inference service: the safety envelope. No transport, metrics or processes."""
