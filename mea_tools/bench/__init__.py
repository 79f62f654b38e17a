"""`mea bench NAME`: one module per benchmark (``cli.BENCHES``), each with a config dataclass and
``run(cfg) -> dict``; ``harness`` (ports, processes, percentiles) and ``report`` (tables, JSON) are
shared by them."""
