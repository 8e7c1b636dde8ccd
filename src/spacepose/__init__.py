"""spacepose: pose and tumbling-motion estimation of non-cooperative space targets from ToF and
flash-LiDAR point clouds."""

from importlib.metadata import PackageNotFoundError, version

from spacepose.core.cloud import PointCloud
from spacepose.errors import (
    ConfigError,
    DegenerateGeometryError,
    FileFormatError,
    InputError,
    RegistrationError,
    SpaceposeError,
)

try:
    __version__ = version("spacepose")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0.0.0"

__all__ = [
    "ConfigError",
    "DegenerateGeometryError",
    "FileFormatError",
    "InputError",
    "PointCloud",
    "RegistrationError",
    "SpaceposeError",
    "__version__",
]
