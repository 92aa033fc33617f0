"""Applications above the three roles: the ``rayfronts`` command dispatcher, the demo,
the paper's evaluation and the benchmarks. They may import ``common``, ``edge``,
``mapper`` and ``query_client``; no role imports ``apps``."""
