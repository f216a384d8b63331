"""Helpers shared by the tests (plain functions and constants; the pytest fixtures are in tests/conftest.py).

Imported as ``tests.helpers.<module>`` (pyproject's ``[tool.pytest.ini_options] pythonpath``)."""
