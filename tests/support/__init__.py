"""Helpers the tests (and some benches) share; tests/ is on sys.path through the root conftest."""
