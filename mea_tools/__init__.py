"""Tools that measure and check the system without being part of it: the benchmarks (`mea bench`,
``bench``) and the physics audit report (`mea audit`, ``audit``). They sit above every service in
the import contracts (pyproject.toml): a tool may import any service, no service imports a tool."""
