"""Full-resolution inputs of ``spacepose bench``: raw ToF frames, the tracker's memory on a stream.

The bench's stage frames are the lab target alone (about 18k points at 640×480). A real ToF camera
returns a point for every pixel: the lab mock-up before its wall (``LabConfig(background=True,
turntable=False)``) seen at the camera's full resolution gives about 300k points at 640×480 and 900k
at 1280×720. The turntable is left out: it moves otherwise than the target, so its frames would be
``degraded`` and time a cheaper step than a healthy one. :func:`raw_frames` renders such frames (the
focal length scaled with the width, so every resolution sees the same horizontal field of view); the
bench times the default tracker's second frame on them beside Open3D's core steps.

:func:`stream_peak_rss` tracks a stream of such frames in a fresh interpreter and reports its
largest resident set, which is what a tracking process needs: the interpreter, numpy, scipy and
the compiled kernels, one raw frame at a time, and the tracker's state.
"""

from __future__ import annotations

import json
import resource
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from spacepose.core.sim import Frame, LabConfig, sensor_config, simulate_lab
from spacepose.errors import SpaceposeError

# Horizontal focal length per pixel of width of the lab's ToF camera (483.6 px at 640 px).
_FOCAL_PER_WIDTH = 483.6 / 640


def raw_frames(width: int, height: int, count: int, seed: int) -> list[Frame]:
    """The first ``count`` frames of the lab run before its wall, every pixel a point.

    Parameters
    ----------
    width, height
        Resolution of the ToF camera (pixels).
    count
        Frames wanted (>= 1).
    seed
        Seed of the simulation.

    Returns
    -------
    The frames (sensor frame, m), rendered one by one as they are asked for.
    """
    sensor = sensor_config("tof", width=width, height=height, focal_px=_FOCAL_PER_WIDTH * width)
    config = LabConfig(frames=count, seed=seed, sensor=sensor, background=True, turntable=False)
    sim = simulate_lab(config)
    return [sim.frame(k) for k in range(count)]


def max_rss_mb() -> float:
    """Largest resident set of this process so far (MB; ``ru_maxrss`` is KiB on Linux)."""
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return rss / 2**20 if sys.platform == "darwin" else rss / 2**10


def stream_peak_rss(frames: list[Frame], workers: int) -> dict:
    """Peak resident memory of a fresh process tracking ``frames`` with the default tracker.

    The frames' points are written to a temporary folder and the child (a new interpreter)
    loads one at a time, as a process reading a camera holds one frame.

    Parameters
    ----------
    frames
        Raw frames (sensor frame) in time order.
    workers
        Threads of the tracker.

    Returns
    -------
    JSON-ready dict: ``frames``, ``points`` (per frame), ``baseline_mb`` (the child's largest
    resident set after its imports, before the first frame), ``peak_mb`` (after the last
    frame) and every frame's ``status``.

    Raises
    ------
    SpaceposeError
        When the child fails (its last line of stderr).
    """
    with tempfile.TemporaryDirectory(prefix="spacepose-bench-") as folder:
        paths = []
        for k, frame in enumerate(frames):
            path = Path(folder) / f"frame_{k:04d}.npy"
            np.save(path, frame.cloud.points)
            paths.append(str(path))
        timestamps = [float(f.timestamp) for f in frames]
        child = subprocess.run(
            [sys.executable, "-c", _CHILD],
            input=json.dumps([paths, timestamps, workers]),
            capture_output=True,
            text=True,
            check=False,
        )
    if child.returncode != 0:
        last = (child.stderr.strip().splitlines() or ["no message"])[-1]
        raise SpaceposeError(f"the tracker's memory run failed: {last}")
    result = json.loads(child.stdout.strip().splitlines()[-1])
    return {"frames": len(frames), "points": [len(f.cloud) for f in frames], **result}


# The child's program: arguments as JSON on stdin, the result as the last line of stdout.
_CHILD = (
    "import json, sys; from spacepose.tools.bench_fullres import _track_stream; "
    "print(json.dumps(_track_stream(*json.load(sys.stdin))))"
)


def _peak_resident_mb() -> float:
    """Largest resident set (MB) of this process image: Linux's ``VmHWM``, which starts afresh
    at ``exec`` (``ru_maxrss`` keeps the forking parent's peak), else ``ru_maxrss``."""
    status = Path("/proc/self/status")
    if status.exists():
        for line in status.read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 2**10
    return max_rss_mb()


def _track_stream(paths: list[str], timestamps: list[float], workers: int) -> dict:
    """In the child: track the saved frames one by one; its resident set before and after."""
    from spacepose.core.tracker import Tracker, TrackerConfig

    baseline = _peak_resident_mb()
    tracker = Tracker(TrackerConfig(), None, workers)
    status = [
        tracker.track_frame(np.load(p), t).status for p, t in zip(paths, timestamps, strict=True)
    ]
    return {"baseline_mb": baseline, "peak_mb": _peak_resident_mb(), "status": status}
