"""Test suite package: makes ``tests.helpers`` importable from the repository root (spawned children too)."""
