"""Benchmarks: each module `bench/<area>.py` has `main(argv) -> int`; records go to bench/results/ (bench/record.py),
bench/RESULTS.md is generated from them (`python -m bench scoreboard`)."""
