"""Benchmarks (``cfbci bench ...``): per-step cost, live latency, floods, soak, memory."""
