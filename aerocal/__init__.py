"""The aerocal engine: everything that turns a flight's images and records into an adjusted block, its
calibration certificate, products and report, and the simulator that proves it finds what it should.

Top-level modules hold the foundations (:mod:`io`, :mod:`tables`, :mod:`geometry`, :mod:`camera`,
:mod:`poses`, :mod:`effects`, :mod:`targets`) and single steps (:mod:`enhance`, :mod:`orient`, :mod:`assess`);
the packages are :mod:`certificates`, :mod:`ingest`, :mod:`formats`, :mod:`matching`, :mod:`adjust`,
:mod:`diagnose`, :mod:`calibrate`, :mod:`products`, :mod:`report`, :mod:`pipeline` (a whole flight in one
process) and :mod:`simulate` (which no processing module imports). The engine knows no Prefect and no SQL:
it imports neither ``flows``, ``tasks`` nor ``storage`` (only :mod:`cli` reaches ``flows``, lazily); the
order in which its units may import each other is ``ENGINE_LAYERS`` in ``tests/test_layers.py``.
"""
