"""The torch layer's commands: everything that parses arguments or writes generated files (``blendsr train``,
``evaluate``, ``upscale``, ``export`` in ``cli``; ``bench models`` and ``bench loader``; the demo's training half;
the generators of derived files, run together by ``generate``). Library modules never import this package
(``tests/system/test_architecture.py``)."""
