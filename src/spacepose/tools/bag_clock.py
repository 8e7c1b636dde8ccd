"""Frame times of a bag topic: header stamps in seconds, or the record times of a topic whose
driver left its stamps unset.

Which one is decided once per topic, from its first messages (:func:`topic_clock`); each
message's time then follows it (:func:`stamp_seconds`); record times are said
(:func:`warn_record_times`). :mod:`spacepose.tools.bag_io` reads the frames.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

from spacepose.errors import InputError, SpaceposeWarning

# A header stamp of zero is unset, not the clock's start, on a clock that reads past a day.
_UNSET_STAMP_CLOCK = 86_400.0


def stamp_seconds(msg: Any, record_time_ns: int, clock: float | None = 0.0) -> float:
    """The header stamp of ``msg`` in seconds; the record time when its topic's stamps are
    unset (``clock`` None: :func:`topic_clock`).

    Raises
    ------
    InputError
        A ``nanosec`` of a second or more: no valid ROS time (a driver writing the whole
        time in nanoseconds there), which moved the frame up to 4 s on without a word; a stamp
        of zero on a clock that reads past a day (``clock``): unset, and it put the frame 1.7e9
        s before the next without a word.
    """
    stamp = msg.header.stamp
    if clock is None:
        return record_time_ns * 1e-9
    if stamp.nanosec >= 1_000_000_000:
        raise InputError(
            f"header stamp nanosec {stamp.nanosec} is a second or more: not a ROS time "
            "(nanosec counts within the second)"
        )
    if stamp.sec == 0 and stamp.nanosec == 0 and clock > _UNSET_STAMP_CLOCK:
        raise InputError(f"header stamp 0 on a clock that reads {clock:.10g} s: unset")
    return stamp.sec + stamp.nanosec * 1e-9


def topic_clock(reader: Any, connections: list[Any], first: int = 3) -> float | None:
    """The largest header stamp (s) of a topic's ``first`` messages, or None when they are all
    stamped zero.

    Decided once per topic: a simulation's clock starting at 0 stamps its first frame 0, and
    that frame taken at its record time (the wall clock, 1.7e9 s) left every later frame "not
    after" it, lost.

    Parameters
    ----------
    reader
        An open ``rosbags`` AnyReader on the bag.
    connections
        The topic's connections.
    first
        How many of the topic's first messages are read.

    Returns
    -------
    float or None
        The largest of their stamps (s); None when they are all zero (a driver that leaves
        stamps unset: the record times are the frame times); 0 when none of them is readable
        (each frame then says why).
    """
    stamps = []
    try:
        for _, (conn, _, raw) in zip(range(first), reader.messages(connections), strict=False):
            try:
                stamp = reader.deserialize(raw, conn.msgtype).header.stamp
            except Exception:  # whatever rosbags meets: the frame itself will say why
                continue
            stamps.append(stamp.sec + stamp.nanosec * 1e-9)
    except Exception:  # a corrupt chunk: the frames will say so
        return 0.0
    if stamps and max(stamps) == 0.0:
        return None
    return max(stamps, default=0.0)


def warn_record_times(topic: str, path: Path) -> None:
    """Say that a topic's frames are timed by their record times (its first stamps unset:
    :func:`topic_clock`). The switch was silent, and it times the later, stamped messages too:
    a driver that stamps from its fourth message on had every frame 0.08 s late (its record
    latency) and none matched a ground truth taken at the stamps. Not counted over the whole
    topic: that would read every message of the bag once more at open.

    Warns
    -----
    SpaceposeWarning
        Naming the bag and topic, pointed at the caller of
        :func:`~spacepose.tools.bag_io.open_bag`.
    """
    warnings.warn(
        SpaceposeWarning(
            f"the first messages on {topic} have no header stamp (0): every frame is timed by "
            "its record time (when the bag wrote it, after the driver's and transport's "
            "latency), any stamped later ones too",
            path,
        ),
        stacklevel=3,
    )
