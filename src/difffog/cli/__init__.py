"""The ``difffog`` command line: ``info``, ``render``, ``fit`` and ``bench`` (one module
each), sharing the parser's scene options and one error path (``_main.py``)."""

from ._main import main as main
