"""A plug-in module that raises while importing (tests/test_plugins.py)."""

raise RuntimeError("this module is broken on purpose")
