"""``companion bench``: every benchmark of the project, apart from the product's modules.

* :mod:`~companion.bench.common`: the sizes, rendered frames, the benchmark calibration, statistics;
* :mod:`~companion.bench.cpu`: the CPU pipeline per stage, the fuzzy controller and the renderer;
* :mod:`~companion.bench.gpu`: the GPU path (``--backend cupy``) against OpenCV on all host cores;
* :mod:`~companion.bench.e2e`: the service's frame-to-setpoint latency (``--e2e``);
* :mod:`~companion.bench.soak`: the service engaged for a long time with operator traffic (``--soak``);
* :mod:`~companion.bench.fuzzy` and :mod:`~companion.bench.render`: the controller and renderer timings.

Speed goals live here and in ``docs/benchmarks.md``, never in timed tests.
"""
