"""The research bench (not shipped in the wheel): data sets in ``../shared/data``, the paper's
front ends, peer filters and the pair protocol used by ``benchmarks/*.py`` and the tests.

Import it with ``benchmarks/`` on ``sys.path`` (the benchmark scripts and pytest do that).
"""
