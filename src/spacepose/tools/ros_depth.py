"""Depth maps in ROS messages: raw ``sensor_msgs/Image`` and ``sensor_msgs/CompressedImage``.

A raw depth image is ``16UC1`` or ``mono16`` (millimetres) or ``32FC1`` (metres), in either byte
order, with row padding. A compressed one is what ``image_transport`` records:

- the ``compressedDepth`` transport (format ``16UC1; compressedDepth png``, older drivers
  ``16UC1; compressedDepth``): a 12-byte header (int32 codec, float32 ``depthQuantA``, float32
  ``depthQuantB``, little-endian) then a 16-bit PNG. A ``16UC1`` map is stored as it is
  (millimetres); a ``32FC1`` map as quantised inverse depth ``q = A / z + B``, so ``z = A /
  (q - B)``, and ``q = 0`` is no return. Its ``rvl`` codec is refused (record with ``png``);
- the ``compressed`` transport of a 16-bit map (format ``16UC1; png compressed …``): a whole
  PNG (or TIFF) of millimetres. A JPEG or any 8-bit or colour image is no depth map, and is
  refused.

Pillow decodes the images (:func:`~spacepose.tools.depth_io.decode_depth_image`); the payload is
told by its PNG signature as well as by the format string, which drivers spell in several ways.
"""

from __future__ import annotations

import struct
from typing import Any

import numpy as np
from numpy.typing import NDArray

from spacepose.errors import FileFormatError
from spacepose.tools.depth_io import decode_depth_image

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
# Depth image encodings -> (numpy kind, metres per unit).
_DEPTH_ENCODINGS = {"16UC1": ("u2", 0.001), "mono16": ("u2", 0.001), "32FC1": ("f4", 1.0)}
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# compressedDepth's header: codec (int32), depthQuantA, depthQuantB (float32), little-endian.
_HEADER = struct.Struct("<iff")
# The transports' topic suffixes (what a compressed topic adds to its raw image's name).
_TRANSPORTS = ("compressedDepth", "compressed")


def depth_values(msg: Any, msgtype: str, source: str) -> tuple[NDArray, float]:
    """The (H, W) values of a depth ``Image`` or ``CompressedImage`` and their metres per unit.

    Parameters
    ----------
    msg
        The deserialised message.
    msgtype
        :data:`IMAGE` or :data:`COMPRESSED_IMAGE`.
    source
        The message (bag, topic, index), named in errors.

    Raises
    ------
    FileFormatError
        An encoding other than ``16UC1`` / ``mono16`` / ``32FC1``, less data than the header
        says, an image that does not decode or is not a 16-bit depth map, the ``rvl`` codec.
    """
    if msgtype == COMPRESSED_IMAGE:
        return compressed_depth(msg, source)
    return image_depth(msg)


def image_depth(msg: Any) -> tuple[NDArray, float]:
    """The (H, W) values of a raw depth ``sensor_msgs/Image`` and their metres per unit.

    Raises
    ------
    FileFormatError
        An encoding other than ``16UC1``/``mono16``/``32FC1``, or less data than the header says.
    """
    if msg.encoding not in _DEPTH_ENCODINGS:
        raise FileFormatError(
            f"depth Image encoding {msg.encoding!r} (supported: {', '.join(_DEPTH_ENCODINGS)})"
        )
    kind, scale = _DEPTH_ENCODINGS[msg.encoding]
    dtype = np.dtype((">" if msg.is_bigendian else "<") + kind)
    data = np.asarray(msg.data, dtype=np.uint8)
    if msg.step < msg.width * dtype.itemsize or data.size < msg.height * msg.step:
        raise FileFormatError(
            f"Image holds {data.size} bytes for {msg.height} rows of step {msg.step}"
        )
    rows = data[: msg.height * msg.step].reshape(msg.height, msg.step)
    values = np.ascontiguousarray(rows[:, : msg.width * dtype.itemsize]).view(dtype)
    return values, scale


def compressed_depth(msg: Any, source: str) -> tuple[NDArray, float]:
    """The (H, W) depths of a ``sensor_msgs/CompressedImage`` and their metres per unit.

    Returns
    -------
    values, scale
        uint16 millimetres and 0.001 for a ``16UC1`` map (or a 16-bit image of a format naming
        no encoding); float32 metres (NaN: no return) and 1.0 for a ``32FC1`` map sent as
        inverse depth, or a float image of a format naming no encoding.

    Raises
    ------
    FileFormatError
        The ``rvl`` codec, another encoding than ``16UC1``/``mono16``/``32FC1`` before the
        ``;``, a payload that is no depth image or not of the named encoding, or a ``32FC1``
        header that decodes its values to no positive depth.
    """
    form = msg.format.strip()
    # "16UC1; compressedDepth png": the map's encoding before the ';' (a bare "png" names none).
    encoding = form.split(";", 1)[0].strip() if ";" in form else ""
    data = np.asarray(msg.data, dtype=np.uint8).tobytes()
    if "rvl" in form.lower():
        raise FileFormatError(
            f"CompressedImage format {form!r}: the RVL depth codec is not read; record the "
            "compressedDepth transport with its png codec"
        )
    header = None
    if data[_HEADER.size : _HEADER.size + 8] == _PNG_SIGNATURE or (
        "compresseddepth" in form.lower() and not data.startswith(_PNG_SIGNATURE)
    ):
        if len(data) < _HEADER.size:
            raise FileFormatError(f"compressedDepth message of {len(data)} bytes: no header")
        header, data = _HEADER.unpack(data[: _HEADER.size]), data[_HEADER.size :]
    if encoding and encoding not in _DEPTH_ENCODINGS:
        raise FileFormatError(
            f"CompressedImage format {form!r} is no depth map (depth encodings: "
            f"{', '.join(_DEPTH_ENCODINGS)})"
        )
    values = decode_depth_image(data, source)
    floats = values.dtype.kind == "f"
    if encoding == "32FC1":
        if header is None:  # a float map cannot travel as an image of the compressed transport
            raise FileFormatError(
                f"CompressedImage format {form!r}: a 32FC1 map without its header"
            )
        if floats:  # the transport quantises: a float image here is no inverse depth
            raise FileFormatError(
                f"CompressedImage format {form!r} carries 16-bit quantised inverse depth, and "
                f"its image holds {values.dtype} values"
            )
        return _inverse_depth(values, *header[1:], form), 1.0
    if floats and encoding:  # 16UC1 said, floats sent: read as millimetres, 1000 times too near
        raise FileFormatError(
            f"CompressedImage format {form!r} says {encoding}, and its image holds "
            f"{values.dtype} values"
        )
    return values, 1.0 if floats else 0.001


def _inverse_depth(values: NDArray, quant_a: float, quant_b: float, form: str) -> NDArray:
    """Depths (float32 m, NaN: no return) of compressedDepth's quantised inverse depths
    ``q``: ``z = A / (q − B)``, refused unless positive and finite wherever ``q > 0`` (a header
    of NaN, or B above the stored values, gave "no return" or negative depths, blamed on the
    pixels)."""
    stored = values.astype(np.float64)
    returns = stored > 0
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        depth = np.where(returns, quant_a / (stored - quant_b), np.nan)
    bad = int(np.count_nonzero(returns & ~(np.isfinite(depth) & (depth > 0))))
    if bad:
        raise FileFormatError(
            f"CompressedImage format {form!r}: its header's depthQuantA {quant_a:g} and "
            f"depthQuantB {quant_b:g} decode {bad} of {int(returns.sum())} stored values to no "
            "positive depth (z = A / (q - B))"
        )
    return depth.astype(np.float32)


def is_depth_format(form: str) -> bool:
    """Whether a ``CompressedImage`` format string can hold a depth map: its encoding (before
    the ``;``) is a depth encoding, or, naming none, its codec is lossless (PNG, TIFF), or it
    is empty (a driver that leaves it so: the image decides)."""
    if ";" in form:
        return form.split(";", 1)[0].strip() in _DEPTH_ENCODINGS
    # A format naming nothing is tried (its image decides); a bare codec must be lossless.
    return not form.strip() or any(c in form.lower() for c in ("png", "tif", "compresseddepth"))


def raw_topic(topic: str) -> str:
    """The raw image topic a transport's topic was published from (``…/image_raw`` of
    ``…/image_raw/compressedDepth``): where its ``CameraInfo`` sits beside it."""
    head, _, last = topic.rpartition("/")
    return head if last in _TRANSPORTS and head else topic
