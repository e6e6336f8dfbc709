"""latticedft benchmarks: serving throughput, training time, long-run fidelity, memory.

Run by hand, never by the test suite (which only smoke-tests ``--quick``)::

    python -m benchmarks [--quick] [--only NAME ...] [--out DIR]

Each benchmark is a small module exposing ``NAME``, ``TITLE`` and
``run(cfg) -> Table``; :mod:`benchmarks.run` prints the tables side by side
with their targets and writes ``results.json`` and ``results.md``
(and figures) into ``--out``.
"""
