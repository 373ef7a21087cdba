"""Fixtures for tests and benchmarks: small synthetic BOP datasets with exact ground truth,
random detector queries, an oracle refiner and its noise ladder.

Not used by the library itself; kept importable so benchmarks and downstream tests can build
the same datasets as our tests.
"""
