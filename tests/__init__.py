"""The test tree (a package, so that pytest puts the repository root, not ``tests/``, on
``sys.path`` for ``tests/conftest.py``: ``tests/lfm_env`` would otherwise shadow ``lfm_env``)."""
