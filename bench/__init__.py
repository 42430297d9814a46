"""Benchmarks: each module `bench/<area>.py` has `main(argv) -> int`; figures go to bench/RESULTS.md."""
