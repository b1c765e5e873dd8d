"""The calibration tests share plain helper modules in this directory (``sample_models``,
``book_tables``); the project runs pytest with ``--import-mode=importlib``, which does not put
test directories on ``sys.path``, so put this one there."""

import sys
from pathlib import Path

_HERE = str(Path(__file__).resolve().parent)
if _HERE not in sys.path:
    sys.path.insert(0, _HERE)
