"""Point clouds in ROS messages: ``sensor_msgs/PointCloud2`` decoded into (N, 3) points.

The ``x``, ``y``, ``z`` fields are read at any offset, of any numeric datatype, in either byte
order, with row padding; NaN points (``is_dense`` false) are kept here, and dropped by the
:class:`~spacepose.core.cloud.PointCloud` made of them. :mod:`spacepose.tools.bag_io` reads
these messages from bags.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from spacepose.errors import FileFormatError
from spacepose.tools.npy_io import as_float64

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
# sensor_msgs/PointField datatypes -> numpy kinds (byte order added per message).
_POINTFIELD_DTYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


def pointcloud2_points(msg: Any) -> NDArray[np.float64]:
    """The (N, 3) ``x, y, z`` of a ``sensor_msgs/PointCloud2`` as float64 (NaN rows kept).

    Raises
    ------
    FileFormatError
        No ``x``/``y``/``z`` field or one named twice, an unknown datatype, or less data than the
        header says.
    """
    fields = {f.name: f for f in msg.fields}
    missing = [name for name in "xyz" if name not in fields]
    if missing:
        raise FileFormatError(f"PointCloud2 without field(s) {', '.join(missing)}")
    twice = [name for name in "xyz" if sum(f.name == name for f in msg.fields) > 1]
    if twice:
        raise FileFormatError(f"PointCloud2 names field {twice[0]} twice")
    order = ">" if msg.is_bigendian else "<"
    names, formats, offsets = [], [], []
    for name in "xyz":
        kind = _POINTFIELD_DTYPES.get(fields[name].datatype)
        if kind is None:
            raise FileFormatError(f"PointCloud2 field {name}: unknown datatype")
        names.append(name)
        formats.append(order + kind)
        offsets.append(fields[name].offset)
    if any(
        o + np.dtype(f).itemsize > msg.point_step for o, f in zip(offsets, formats, strict=True)
    ):
        raise FileFormatError(f"PointCloud2 fields reach past point_step {msg.point_step}")
    point = np.dtype(
        {"names": names, "formats": formats, "offsets": offsets, "itemsize": msg.point_step}
    )
    rows, width, row_step = msg.height, msg.width, msg.row_step
    data = np.asarray(msg.data, dtype=np.uint8)
    if row_step < width * msg.point_step or data.size < rows * row_step:
        raise FileFormatError(
            f"PointCloud2 holds {data.size} bytes for {rows}x{width} points of "
            f"{msg.point_step} bytes (row_step {row_step})"
        )
    table = data[: rows * row_step].reshape(rows, row_step)[:, : width * msg.point_step]
    records = np.ascontiguousarray(table).view(point).reshape(-1)
    return np.column_stack([as_float64(records[n]) for n in names])
