"""Benchmarks of cmion_mesh against raw zenoh, measured in the same run on the same machine.

Run ``python -m bench`` from the repository root; see ``bench/README.md`` for the method.
Benchmarks are registered in ``bench.registry.BENCHMARKS`` (one entry per module).

This package deliberately imports none of its benchmark modules: they are loaded on demand,
so that ``python -m bench.core serve-...`` (the child processes) imports only what it needs.
"""
