"""Makes ``rfcl_sim`` resolve to this checkout's package (python/rfcl_sim), whatever directory
pytest runs from: the venv's editable install may point at another copy of the repository."""
import sys
from pathlib import Path

_PACKAGE_ROOT = str(Path(__file__).resolve().parents[1])
if _PACKAGE_ROOT not in sys.path:
    sys.path.insert(0, _PACKAGE_ROOT)
