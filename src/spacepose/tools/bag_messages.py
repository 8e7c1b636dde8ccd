"""Reading a bag's messages (``rosbags``' reader), a damaged chunk named as the bag's fault."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

from spacepose.errors import FileFormatError


def bag_messages(reader: Any, connections: list[Any], path: Path) -> Iterator[tuple]:
    """``reader.messages(connections)``, a damaged chunk a :class:`FileFormatError` naming the
    bag: rosbags raises what its decompressor or parser meets (``OSError('Invalid data
    stream')`` for a damaged bz2 chunk), which reached the user as a traceback."""
    messages = reader.messages(connections)
    while True:
        try:
            item = next(messages)
        except StopIteration:
            return
        except Exception as exc:  # whatever rosbags meets in a bad chunk
            raise FileFormatError(f"cannot read the bag's messages: {exc}", path) from None
        yield item
