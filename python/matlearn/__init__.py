"""matlearn: learn elastic and damping corrections from sparse recordings of soft objects."""
from . import _core  # noqa: F401

__version__ = "0.1.0"
