"""Make the repository importable when the project is not installed (``pip install -e .``)."""

import importlib.util
import sys
from pathlib import Path

if importlib.util.find_spec("drivers") is None or importlib.util.find_spec("fakes") is None:
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
