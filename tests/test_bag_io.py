"""ROS 1 / ROS 2 bags as frames (tools/bag_io.py), written here with rosbags' own writers."""

from __future__ import annotations

import io
import struct
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore

from spacepose.cli import main
from spacepose.core.depth import DepthCamera, render_depth
from spacepose.core.sim import scenario_config, simulate
from spacepose.errors import FileFormatError, InputError, SpaceposeWarning
from spacepose.tools.bag_camera import camera_from_info
from spacepose.tools.bag_io import open_bag
from spacepose.tools.intrinsics_io import read_intrinsics
from spacepose.tools.ros_pointcloud import pointcloud2_points
from spacepose.tools.tracking_io import track_folder, tracker_config
from spacepose.tools.trajectory_io import read_tum

N_FRAMES = 6
ROS2 = get_typestore(Stores.ROS2_HUMBLE)
ROS1 = get_typestore(Stores.ROS1_NOETIC)
PC2 = "sensor_msgs/msg/PointCloud2"
IMAGE = "sensor_msgs/msg/Image"
INFO = "sensor_msgs/msg/CameraInfo"
COMPRESSED = "sensor_msgs/msg/CompressedImage"


def _stamp(k: int) -> tuple[int, int]:
    return 1_700_000_000 + k // 4, (k % 4) * 250_000_000


def _header(store, k: int):
    T = store.types
    sec, nanosec = _stamp(k)
    extra = {"seq": k} if "seq" in T["std_msgs/msg/Header"].__dataclass_fields__ else {}
    return T["std_msgs/msg/Header"](
        stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id="tof", **extra
    )


def _pointcloud2(store, k: int, grid: np.ndarray, datatype: int = 7, bigendian: bool = False):
    """An organised PointCloud2 (H, W) of x, y, z and intensity, NaN where no return."""
    T = store.types
    kind = {7: "f4", 8: "f8"}[datatype]
    order = ">" if bigendian else "<"
    size = np.dtype(kind).itemsize
    record = np.dtype(
        {
            "names": ["x", "y", "z", "intensity"],
            "formats": [order + kind] * 3 + [order + "f4"],
            "offsets": [0, size, 2 * size, 3 * size],
            "itemsize": 3 * size + 4 + 4,  # 4 bytes of padding after intensity
        }
    )
    h, w = grid.shape[:2]
    table = np.zeros(h * w, dtype=record)
    for i, name in enumerate("xyz"):
        table[name] = grid.reshape(-1, 3)[:, i]
    fields = [
        T["sensor_msgs/msg/PointField"](name=n, offset=o, datatype=d, count=1)
        for n, o, d in zip("xyz", (0, size, 2 * size), (datatype,) * 3, strict=True)
    ]
    fields.append(
        T["sensor_msgs/msg/PointField"](name="intensity", offset=3 * size, datatype=7, count=1)
    )
    return T[PC2](
        header=_header(store, k), height=h, width=w, fields=fields, is_bigendian=bigendian,
        point_step=record.itemsize, row_step=record.itemsize * w,
        data=np.frombuffer(table.tobytes(), dtype=np.uint8), is_dense=False,
    )  # fmt: skip


def _image(store, k: int, millimetres: np.ndarray):
    h, w = millimetres.shape
    return store.types[IMAGE](
        header=_header(store, k), height=h, width=w, encoding="16UC1", is_bigendian=0,
        step=2 * w, data=np.frombuffer(millimetres.astype("<u2").tobytes(), dtype=np.uint8),
    )  # fmt: skip


def _camera_info(store, camera: DepthCamera, ros1: bool):
    T = store.types
    K = np.array([camera.fx, 0, camera.cx, 0, camera.fy, camera.cy, 0, 0, 1.0])
    arrays = {"d": np.zeros(5), "k": K, "r": np.eye(3).ravel(), "p": np.zeros(12)}
    if ros1:
        arrays = {key.upper(): value for key, value in arrays.items()}
    return T[INFO](
        header=_header(store, 0), height=camera.height, width=camera.width,
        distortion_model="plumb_bob", binning_x=0, binning_y=0,
        roi=T["sensor_msgs/msg/RegionOfInterest"](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        ),
        **arrays,
    )  # fmt: skip


def _write(path: Path, messages: list[tuple[str, str, object]], ros1: bool = False, mcap=True):
    """Write (topic, msgtype, message) in order, 0.1 s apart in record time."""
    store = ROS1 if ros1 else ROS2
    if ros1:
        writer = Writer1(path)
    else:
        plugin = StoragePlugin.MCAP if mcap else StoragePlugin.SQLITE3
        writer = Writer2(path, version=9, storage_plugin=plugin)
    serialize = store.serialize_ros1 if ros1 else store.serialize_cdr
    with writer:
        connections: dict[str, object] = {}
        for i, (topic, msgtype, msg) in enumerate(messages):
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=store)
            writer.write(connections[topic], 10**9 + i * 10**8, serialize(msg, msgtype))
    return path


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    """Six lab frames as (H, W, 3) float32 point grids and as millimetre depth images, the
    ROS 2 bag holding both, and each one's equivalent .npy cloud folder."""
    sim = simulate(scenario_config("lab", frames=N_FRAMES))
    s = sim.config.sensor
    camera = DepthCamera(
        fx=s.focal_px, fy=s.focal_px, cx=0.5 * (s.width - 1), cy=0.5 * (s.height - 1),
        width=s.width, height=s.height,
    )  # fmt: skip
    root = tmp_path_factory.mktemp("bags")
    messages = [("/tof/depth/camera_info", INFO, _camera_info(ROS2, camera, ros1=False))]
    grids, depths = [], []
    for k in range(N_FRAMES):
        depth_m = render_depth(sim.frame(k).cloud.points, camera, s.height, s.width)
        millimetres = np.rint(depth_m * 1000).astype(np.uint16)
        v, u = np.mgrid[0 : s.height, 0 : s.width]
        z = np.where(depth_m > 0, depth_m, np.nan)
        grid = np.stack([(u - camera.cx) / camera.fx * z, (v - camera.cy) / camera.fy * z, z], -1)
        grids.append(grid.astype(np.float32))
        depths.append(millimetres)
        messages.append(("/tof/points", PC2, _pointcloud2(ROS2, k, grids[-1])))
        messages.append(("/tof/depth/image_raw", IMAGE, _image(ROS2, k, millimetres)))
    bag = _write(root / "ros2_bag", messages)
    equivalents = {"points": root / "points", "image": root / "image"}
    for folder in equivalents.values():
        folder.mkdir()
        (folder / "timestamps.txt").write_text(
            "".join(f"{s_ + ns * 1e-9!r}\n" for s_, ns in map(_stamp, range(N_FRAMES)))
        )
    for k in range(N_FRAMES):
        points = grids[k].reshape(-1, 3).astype(np.float64)
        np.save(equivalents["points"] / f"{k:03d}.npy", points[np.isfinite(points[:, 2])])
        v, u = np.nonzero(depths[k])
        z = depths[k][v, u] * 0.001
        xyz = np.column_stack([(u - camera.cx) / camera.fx * z, (v - camera.cy) / camera.fy * z, z])
        np.save(equivalents["image"] / f"{k:03d}.npy", xyz)
    return {"bag": bag, "camera": camera, "grids": grids, "root": root, **equivalents}


@pytest.mark.parametrize(
    ("topic", "equivalent"), [("/tof/points", "points"), ("/tof/depth/image_raw", "image")]
)
def test_ros2_bag_tracks_like_the_cloud_folder(lab, tmp_path, capsys, topic, equivalent):
    out = tmp_path / "bag.tum"
    code = main(["track", str(lab["bag"]), "--out", str(out), "--topic", topic])
    assert code == 0, capsys.readouterr().err
    ref = track_folder(lab[equivalent], tmp_path / "ref.tum", tracker_config())
    assert ref["lost"] == 0
    est, expected = read_tum(out), read_tum(tmp_path / "ref.tum")
    # Header stamps, carried to the TUM file.
    stamps = [s + ns * 1e-9 for s, ns in map(_stamp, range(N_FRAMES))]
    np.testing.assert_array_equal(est.timestamps, stamps)
    assert np.max(np.abs(est.poses - expected.poses)) < 1e-9


def test_topic_must_be_chosen_among_the_frame_topics(lab, tmp_path, capsys):
    out = str(tmp_path / "x.tum")
    assert main(["track", str(lab["bag"]), "--out", out]) == 1
    err = capsys.readouterr().err.strip()
    assert "2 PointCloud2/Image topics, choose one with --topic" in err
    assert "/tof/depth/image_raw (Image), /tof/points (PointCloud2)" in err and "\n" not in err
    with pytest.raises(InputError, match=r"/tof/depth/camera_info is a sensor_msgs/msg/CameraInfo"):
        open_bag(lab["bag"], topic="/tof/depth/camera_info")
    with pytest.raises(InputError, match=r"/nope is not in the bag; frame topics: /tof/depth"):
        open_bag(lab["bag"], topic="/nope")
    assert not (tmp_path / "x.tum").exists()


def test_intrinsics_for_a_pointcloud2_topic_are_refused(lab, tmp_path, capsys):
    """They used to be ignored without a word: a user who meant the depth topic got the
    points tracked and believed their intrinsics applied."""
    intrinsics = tmp_path / "intrinsics.yaml"
    intrinsics.write_text("fx: 500\nfy: 500\ncx: 320\ncy: 240\ndepth_scale: 0.001\n")
    out = tmp_path / "x.tum"
    args = ["track", str(lab["bag"]), "--out", str(out), "--topic", "/tof/points"]
    assert main([*args, "--intrinsics", str(intrinsics)]) == 1
    err = capsys.readouterr().err.strip()
    assert err.endswith(
        "ros2_bag: intrinsics apply to depth images, and /tof/points is a PointCloud2 (points "
        "in metres): leave out --intrinsics, or choose an Image topic"
    ), err
    assert "\n" not in err and not out.exists()
    # An Image topic takes them only if they agree with its CameraInfo (round 21).
    with pytest.raises(InputError, match=r"CameraInfo on /tof/depth/camera_info differ \(fx 500"):
        open_bag(lab["bag"], "/tof/depth/image_raw", read_intrinsics(intrinsics))


def test_image_topic_uses_camera_info(lab):
    frames = open_bag(lab["bag"], topic="/tof/depth/image_raw")
    assert frames.camera.fx == lab["camera"].fx and frames.camera.cx == lab["camera"].cx
    assert (frames.camera.width, frames.camera.height) == (640, 480)
    first = next(iter(frames))
    z = lab["grids"][0][..., 2]
    assert len(first.cloud) == int(np.isfinite(z).sum())
    np.testing.assert_allclose(
        np.sort(first.cloud.points[:, 2]), np.sort(z[np.isfinite(z)]), atol=5e-4
    )


def test_ros1_bag(lab, tmp_path):
    grid = lab["grids"][0][::4, ::4]
    millimetres = np.rint(np.nan_to_num(grid[..., 2]) * 1000).astype(np.uint16)
    camera = lab["camera"].model_copy(
        update={"fx": lab["camera"].fx / 4, "fy": lab["camera"].fy / 4, "width": 160, "height": 120}
        | {"cx": lab["camera"].cx / 4, "cy": lab["camera"].cy / 4}  # pixel 4u of the full grid
    )
    bag = _write(
        tmp_path / "run.bag",
        [
            ("/cam/camera_info", INFO, _camera_info(ROS1, camera, ros1=True)),
            ("/cam/depth", IMAGE, _image(ROS1, 0, millimetres)),
            ("/cam/points", PC2, _pointcloud2(ROS1, 0, grid, datatype=8)),
            ("/cam/depth", IMAGE, _image(ROS1, 1, millimetres)),
        ],
        ros1=True,
    )
    points = list(open_bag(bag, topic="/cam/points"))
    assert len(points) == 1 and points[0].timestamp == 1_700_000_000.0
    finite = grid.reshape(-1, 3)[np.isfinite(grid[..., 2]).ravel()]
    np.testing.assert_array_equal(points[0].cloud.points, finite.astype(np.float64))
    depth = list(open_bag(bag, topic="/cam/depth"))
    assert [f.timestamp for f in depth] == [1_700_000_000.0, 1_700_000_000.25]
    assert depth[0].cloud is not None and len(depth[0].cloud) == len(finite)
    np.testing.assert_allclose(depth[0].cloud.points, finite, atol=1e-3)


def test_pointcloud2_layouts():
    rng = np.random.default_rng(5)
    grid = rng.normal(size=(3, 4, 3))
    grid[1, 2] = np.nan
    for datatype, bigendian in ((7, True), (8, False), (8, True)):
        msg = _pointcloud2(ROS2, 0, grid, datatype=datatype, bigendian=bigendian)
        points = pointcloud2_points(ROS2.deserialize_cdr(ROS2.serialize_cdr(msg, PC2), PC2))
        expected = grid.reshape(-1, 3).astype("f4" if datatype == 7 else "f8")
        np.testing.assert_array_equal(points, expected.astype(np.float64))
    # Row padding: row_step beyond width * point_step.
    msg = _pointcloud2(ROS2, 0, grid)
    padded = np.concatenate(
        [np.frombuffer(msg.data, np.uint8).reshape(3, -1), np.zeros((3, 8), np.uint8)], 1
    )
    msg.data, msg.row_step = padded.ravel(), msg.row_step + 8
    np.testing.assert_array_equal(pointcloud2_points(msg), grid.reshape(-1, 3).astype("f4"))
    msg.data = msg.data[:-50]
    with pytest.raises(FileFormatError, match="bytes for 3x4 points"):
        pointcloud2_points(msg)
    msg.fields = msg.fields[:2]
    with pytest.raises(FileFormatError, match="without field"):
        pointcloud2_points(msg)


def test_camera_info_distortion():
    camera = DepthCamera(fx=500.0, fy=500.0, cx=319.5, cy=239.5, width=640, height=480)
    info = _camera_info(ROS2, camera, ros1=False)
    info.d = np.array([-0.1, 0.02, 0.001, -0.002, 0.003, 0.01, 0.0, 0.001])
    info.distortion_model = "rational_polynomial"
    got = camera_from_info(info, depth_scale=0.001)
    assert (got.k1, got.k2, got.p1, got.p2, got.k3, got.k4, got.k6) == (
        -0.1, 0.02, 0.001, -0.002, 0.003, 0.01, 0.001
    )  # fmt: skip
    info.distortion_model = "equidistant"
    with pytest.raises(FileFormatError, match="equidistant"):
        camera_from_info(info, depth_scale=0.001)


def test_bad_messages_are_lost_and_the_rest_tracked(lab, tmp_path):
    """Frame 2 has no z field, frame 3 only NaN points: both lost, with their reasons; the
    ROS 2 bag is sqlite3 this time."""
    messages = []
    for k in range(N_FRAMES):
        grid = lab["grids"][k]
        if k == 3:
            grid = np.full_like(grid[:4, :4], np.nan)
        msg = _pointcloud2(ROS2, k, grid)
        if k == 2:
            msg.fields = msg.fields[:2]
        messages.append(("/points", PC2, msg))
    bag = _write(tmp_path / "bad_bag", messages, mcap=False)
    summary = track_folder(bag, tmp_path / "est.tum", tracker_config())
    assert (summary["frames"], summary["lost"]) == (N_FRAMES, 2)
    health = (tmp_path / "est.health.csv").read_text().splitlines()
    assert "without field(s) z" in health[3] and ",lost," in health[3]
    assert "no finite point" in health[4] and ",lost," in health[4]
    assert len(read_tum(tmp_path / "est.tum")) == N_FRAMES


def test_a_frame_stamped_out_of_order_is_lost_and_the_rest_tracked(lab, tmp_path):
    """Header stamps are read as the frames come: frame 2 stamped as frame 1 (a repeat) and
    frame 4 as frame 0 (a step back) are lost with the reason and left out of the trajectory,
    whose times rise; every other frame is tracked as in order."""
    stamps = {2: 1, 4: 0}
    messages = []
    for k in range(N_FRAMES):
        msg = _pointcloud2(ROS2, k, lab["grids"][k])
        msg.header = _header(ROS2, stamps.get(k, k))
        messages.append(("/points", PC2, msg))
    bag = _write(tmp_path / "stamps_bag", messages)
    # Said on stderr too, as an unreadable frame is (the table alone held it).
    with pytest.warns(SpaceposeWarning, match=r"points#4: frame lost: timestamp .* does not come"):
        summary = track_folder(bag, tmp_path / "est.tum", tracker_config())
    assert (summary["frames"], summary["lost"]) == (N_FRAMES, 2)
    health = (tmp_path / "est.health.csv").read_text().splitlines()[1:]
    assert "repeats the last tracked one" in health[2] and ",lost," in health[2]
    assert "does not come after the last tracked one" in health[4] and ",lost," in health[4]
    assert [row.split(",")[2] for row in health].count("lost") == 2
    times = read_tum(tmp_path / "est.tum").timestamps
    assert len(times) == N_FRAMES - 2 and np.all(np.diff(times) > 0)


def test_a_message_rosbags_cannot_deserialize_is_lost_and_the_rest_tracked(lab, tmp_path):
    """A message whose bytes are not a PointCloud2 (here a sqlite3 row overwritten) raised
    rosbags' AnyReaderError out of the run: a traceback, and the frames after it unwritten."""
    import sqlite3

    grids = [g[::4, ::4] for g in lab["grids"]]
    bag = _write(tmp_path / "blob_bag", [("/points", PC2, _pointcloud2(ROS2, k, g))
                                         for k, g in enumerate(grids)], mcap=False)  # fmt: skip
    (db,) = bag.glob("*.db3")
    with sqlite3.connect(db) as con:
        ids = [row[0] for row in con.execute("SELECT id FROM messages ORDER BY id")]
        con.execute("UPDATE messages SET data = ? WHERE id = ?", (b"\x00\x01\x00\x00x", ids[2]))
    out = tmp_path / "est.tum"
    summary = track_folder(bag, out, tracker_config())
    assert (summary["frames"], summary["lost"]) == (N_FRAMES, 1)
    health = (tmp_path / "est.health.csv").read_text().splitlines()
    assert ",lost," in health[3] and "cannot decode the message: Could not deserialize" in health[3]


def test_a_corrupt_chunk_loses_the_frames_it_ends_and_says_so(lab, tmp_path, capsys):
    """A ROS 1 bag whose third bz2 chunk is damaged: rosbags' reader raised OSError('Invalid
    data stream') mid-run, printed without the bag's name, and the last frames had no row.
    Now every frame has its row, those from the damaged chunk on lost with the reason."""
    grids = [g[::4, ::4] for g in lab["grids"]]
    path = tmp_path / "run.bag"
    writer = Writer1(path)
    writer.set_compression(Writer1.CompressionFormat.BZ2)
    writer.chunk_threshold = 1  # one message a chunk
    with writer:
        conn = writer.add_connection("/points", PC2, typestore=ROS1)
        for k, g in enumerate(grids):
            msg = ROS1.serialize_ros1(_pointcloud2(ROS1, k, g), PC2)
            writer.write(conn, 10**9 + k * 10**8, msg)
    data = bytearray(path.read_bytes())
    starts = [i for i in range(len(data)) if data.startswith(b"BZh", i)]
    data[starts[2] + 10 : starts[2] + 400] = bytes(390)
    path.write_bytes(bytes(data))
    out = tmp_path / "est.tum"
    assert main(["track", str(path), "--out", str(out)]) == 0, capsys.readouterr().err
    rows = (tmp_path / "est.health.csv").read_text().splitlines()[1:]
    assert len(rows) == N_FRAMES
    assert [r.split(",")[2] for r in rows[2:]] == ["lost"] * (N_FRAMES - 2)
    assert all("cannot read the bag from message #2 on" in r for r in rows[2:])
    assert [r.split(",")[2] != "lost" for r in rows[:2]] == [True, True]
    assert len(read_tum(out)) == 2  # the unread frames have no time: no pose is made up


def test_a_topic_without_messages_says_so(tmp_path, capsys):
    """A frame topic declared but never published: one line, and no outputs begun."""
    path = tmp_path / "empty_bag"
    with Writer2(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        writer.add_connection("/points", PC2, typestore=ROS2)
    out = tmp_path / "out" / "est.tum"
    assert main(["track", str(path), "--out", str(out)]) == 1
    err = capsys.readouterr().err.strip()
    assert err.endswith("empty_bag: no messages on /points: the bag holds no frame"), err
    assert not out.parent.exists()


def test_a_bag_without_frame_topics_says_so(lab, tmp_path, capsys):
    """An empty bag, or one of CameraInfo only, told the user to choose among "none" with
    --topic."""
    empty = tmp_path / "empty_bag"
    with Writer2(empty, version=9, storage_plugin=StoragePlugin.MCAP):
        pass
    camera = lab["camera"]
    info_only = _write(
        tmp_path / "info_bag", [("/cam/info", INFO, _camera_info(ROS2, camera, False))]
    )
    for bag, held in ((empty, "none"), (info_only, "/cam/info (CameraInfo)")):
        assert main(["track", str(bag), "--out", str(tmp_path / "e.tum")]) == 1
        err = capsys.readouterr().err.strip()
        assert err.endswith(
            f"no PointCloud2/Image topic: the bag holds no frame (its topics: {held})"
        ), err
        assert "--topic" not in err


@pytest.mark.parametrize(
    ("content", "problem"),
    [
        (b"", "cannot open the bag"),
        # rosbags said "'utf-8' codec can't decode byte 0x9d" of random bytes.
        (b"not a bag at all\n", "not a ROS 1 bag: it begins with b'not a ba'"),
        (bytes([0x9D, 0x83, 0xE9, 0x22]) * 64, "not a ROS 1 bag: it begins with b'\\x9d"),
    ],
)
def test_unreadable_bag_is_one_line(tmp_path, capsys, content, problem):
    (tmp_path / "run.bag").write_bytes(content)
    assert main(["track", str(tmp_path / "run.bag"), "--out", str(tmp_path / "e.tum")]) == 1
    err = capsys.readouterr().err.strip()
    assert f"run.bag: {problem}" in err and "\n" not in err, err


def test_a_ros2_bag_with_an_empty_metadata_file_says_so(tmp_path, capsys):
    """rosbags said "'NoneType' object is not subscriptable"."""
    bag = tmp_path / "run"
    bag.mkdir()
    (bag / "metadata.yaml").write_text("\n")
    assert main(["track", str(bag), "--out", str(tmp_path / "e.tum")]) == 1
    err = capsys.readouterr().err.strip()
    assert err == f"error: {bag}: not a ROS 2 bag: its metadata.yaml is empty", err


# --------------------------------------------------------------------------------------------
# Compressed depth: what image_transport records (compressedDepth and compressed transports)


def _png(values: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(values).save(buffer, format="PNG")
    return buffer.getvalue()


def _compressed(store, k: int, form: str, payload: bytes):
    return store.types[COMPRESSED](
        header=_header(store, k), format=form, data=np.frombuffer(payload, dtype=np.uint8)
    )


def _quantised_inverse(depth_m: np.ndarray, quantization=100.0, depth_max=10.0):
    """compressed_depth_image_transport's encoding of a 32FC1 map (its defaults): the header
    and the 16-bit inverse depth q = A / z + B, 0 where no return."""
    a = quantization * (quantization + 1.0)
    b = 1.0 - a / depth_max
    with np.errstate(divide="ignore"):
        q = np.where(depth_m > 0, np.rint(a / depth_m + b), 0).astype(np.uint16)
    return struct.pack("<iff", 0, a, b) + _png(q), a


@pytest.mark.parametrize("ros1", [False, True])
def test_compressed_depth_topics_track_like_the_raw_image(lab, tmp_path, capsys, ros1):
    """A 16UC1 map through the compressedDepth transport (header + PNG) and through the
    compressed one (a PNG) gives the raw Image topic's clouds to the bit; a JPEG colour stream
    beside them is no frame topic, and is refused by name."""
    store = ROS1 if ros1 else ROS2
    camera = lab["camera"]
    jpeg = io.BytesIO()
    Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(jpeg, format="JPEG")
    messages = [("/cam/depth/camera_info", INFO, _camera_info(store, camera, ros1=ros1))]
    for k in range(3):
        millimetres = np.rint(np.nan_to_num(lab["grids"][k][..., 2]) * 1000).astype(np.uint16)
        header = struct.pack("<iff", 0, 0.0, 0.0)
        messages += [
            ("/cam/depth/image_raw", IMAGE, _image(store, k, millimetres)),
            ("/cam/depth/image_raw/compressedDepth", COMPRESSED,
             _compressed(store, k, "16UC1; compressedDepth png", header + _png(millimetres))),
            ("/cam/depth/image_raw/compressed", COMPRESSED,
             _compressed(store, k, "16UC1; png compressed mono16", _png(millimetres))),
            ("/cam/color/compressed", COMPRESSED,
             _compressed(store, k, "rgb8; jpeg compressed bgr8", jpeg.getvalue())),
        ]  # fmt: skip
    bag = _write(tmp_path / ("run.bag" if ros1 else "run"), messages, ros1=ros1)
    raw = [f.cloud.points for f in open_bag(bag, "/cam/depth/image_raw")]
    for topic in ("/cam/depth/image_raw/compressedDepth", "/cam/depth/image_raw/compressed"):
        frames = list(open_bag(bag, topic))
        assert [f.error for f in frames] == [None] * 3
        assert frames[0].timestamp == 1_700_000_000.0
        for frame, points in zip(frames, raw, strict=True):
            np.testing.assert_array_equal(frame.cloud.points, points)
    with pytest.raises(InputError, match=r"/cam/color/compressed carries 'rgb8; jpeg compr"):
        open_bag(bag, "/cam/color/compressed")
    # Three depth topics to choose from; the colour stream is not listed among them.
    assert main(["track", str(bag), "--out", str(tmp_path / "e.tum")]) == 1
    err = capsys.readouterr().err
    assert "3 PointCloud2/Image topics" in err and "/cam/color" not in err, err


def test_a_32fc1_compressed_depth_map_is_its_inverse_depth_decoded(lab, tmp_path):
    """32FC1 through compressedDepth is quantised inverse depth: decoded z is within the
    quantisation step z² / (2A) of the map, and no return stays no return."""
    z = lab["grids"][0][..., 2].astype(np.float64)
    payload, a = _quantised_inverse(np.nan_to_num(z))
    message = _compressed(ROS2, 0, "32FC1; compressedDepth png", payload)
    info = _camera_info(ROS2, lab["camera"], ros1=False)
    topic = "/cam/depth/image_raw/compressedDepth"
    bag = _write(
        tmp_path / "run", [("/cam/depth/camera_info", INFO, info), (topic, COMPRESSED, message)]
    )
    (frame,) = list(open_bag(bag))
    finite = np.isfinite(z)
    assert len(frame.cloud) == int(finite.sum())
    got, expected = np.sort(frame.cloud.points[:, 2]), np.sort(z[finite])
    step = expected**2 / (2 * a)
    assert np.all(np.abs(got - expected) <= step * 1.01 + 1e-6)
    assert np.abs(got - expected).max() > 0.2 * step.max()  # quantised, not passed through


def test_an_rvl_or_undecodable_compressed_depth_frame_is_lost_and_the_rest_read(lab, tmp_path):
    millimetres = np.rint(np.nan_to_num(lab["grids"][0][..., 2]) * 1000).astype(np.uint16)
    good = struct.pack("<iff", 0, 0.0, 0.0) + _png(millimetres)
    forms = [
        ("16UC1; compressedDepth png", good),
        ("16UC1; compressedDepth rvl", good[:40]),
        ("16UC1; compressedDepth png", good[:200]),  # truncated PNG
        ("16UC1; compressedDepth png", good),
    ]
    messages = [("/cam/depth/camera_info", INFO, _camera_info(ROS2, lab["camera"], ros1=False))]
    for k, (form, payload) in enumerate(forms):
        message = _compressed(ROS2, k, form, payload)
        messages.append(("/cam/depth/image_raw/compressedDepth", COMPRESSED, message))
    bag = _write(tmp_path / "run", messages)
    frames = list(open_bag(bag))
    assert [f.cloud is not None for f in frames] == [True, False, False, True]
    assert "RVL depth codec is not read" in frames[1].error
    assert "cannot decode the image" in frames[2].error


def _restamped(msg, sec: int, nanosec: int):
    msg.header.stamp = ROS2.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)
    return msg


def test_a_clock_from_zero_is_the_header_stamps_and_unset_stamps_the_record_times(lab, tmp_path):
    """A simulation's clock stamps its first frame 0: that frame used to take its record time
    (1e9 s here, the wall clock in a real bag) and every later frame, stamped 0.1 s on, was
    lost as "not after" it. A topic whose stamps are all unset takes the record times."""
    grid = lab["grids"][0][::8, ::8]
    sim_clock = [("/points", PC2, _restamped(_pointcloud2(ROS2, k, grid), 0, k * 10**8))
                 for k in range(4)]  # fmt: skip
    frames = list(open_bag(_write(tmp_path / "sim", sim_clock)))
    np.testing.assert_allclose([f.timestamp for f in frames], [0.0, 0.1, 0.2, 0.3], atol=1e-12)
    unset = [("/points", PC2, _restamped(_pointcloud2(ROS2, k, grid), 0, 0)) for k in range(4)]
    frames = list(open_bag(_write(tmp_path / "unset", unset)))
    # _write's record times
    np.testing.assert_allclose([f.timestamp for f in frames], [1.0, 1.1, 1.2, 1.3], atol=1e-12)


def test_every_message_is_read_whatever_the_metadata_counts(lab, tmp_path):
    """A metadata.yaml counting 1 of 3 messages read 1 frame without a word; counting 0, the
    bag was refused as holding none."""
    grid = lab["grids"][0][::8, ::8]
    messages = [("/points", PC2, _pointcloud2(ROS2, k, grid)) for k in range(3)]
    bag = _write(tmp_path / "run", messages, mcap=False)
    metadata = bag / "metadata.yaml"
    text = metadata.read_text()
    assert "message_count: 3" in text
    metadata.write_text(text.replace("message_count: 3", "message_count: 1"))
    with pytest.warns(SpaceposeWarning, match=r"counts 1 messages on /points and holds 3: all 3"):
        frames = list(open_bag(bag))
    assert [f.error for f in frames] == [None] * 3
    metadata.write_text(text.replace("message_count: 3", "message_count: 0"))
    frames = open_bag(bag)
    assert len(frames) == 3 and [f.error for f in frames] == [None] * 3


def test_a_ros2_recording_without_its_metadata_says_so(lab, tmp_path, capsys):
    bag = _write(tmp_path / "run", [("/points", PC2, _pointcloud2(ROS2, 0, lab["grids"][0]))],
                 mcap=False)  # fmt: skip
    (bag / "metadata.yaml").unlink()
    assert main(["track", str(bag), "--out", str(tmp_path / "e.tum")]) == 1
    err = capsys.readouterr().err.strip()
    assert err.endswith(
        "run: holds run.db3 but no metadata.yaml: a ROS 2 bag whose recording did not finish? "
        "(`ros2 bag reindex` writes it)"
    ), err


def _tiff(values: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(values).save(buffer, format="TIFF")
    return buffer.getvalue()


def test_compressed_payloads_that_contradict_their_format_are_lost_by_name(lab, tmp_path):
    """Each was decoded without a word: a float image in 32FC1's compressedDepth as inverse
    depth (a wall at 10 m), a header of NaN as "no return", a float TIFF said 16UC1 as
    millimetres (every pose 1000 times too short). A float TIFF of a format naming no
    encoding is metres, and a PNG of an empty format is read."""
    z = np.nan_to_num(lab["grids"][0][..., 2]).astype(np.float32)
    millimetres = np.rint(z * 1000).astype(np.uint16)
    quantised, _ = _quantised_inverse(z.astype(np.float64))
    nan_header = struct.pack("<iff", 0, np.nan, np.nan) + quantised[12:]
    forms = [
        ("32FC1; compressedDepth png", struct.pack("<iff", 0, 10100.0, -1009.0) + _tiff(z)),
        ("32FC1; compressedDepth png", nan_header),
        ("16UC1; tiff compressed", _tiff(z)),
        ("tiff", _tiff(z)),
        ("", _png(millimetres)),
    ]
    info = _camera_info(ROS2, lab["camera"], ros1=False)
    messages = [("/cam/depth/camera_info", INFO, info)]
    for k, (form, payload) in enumerate(forms):
        messages.append(
            ("/cam/depth/image_raw/compressed", COMPRESSED, _compressed(ROS2, k, form, payload))
        )
    frames = list(open_bag(_write(tmp_path / "run", messages)))
    assert "carries 16-bit quantised inverse depth, and its image holds float32" in frames[0].error
    assert "depthQuantA nan and depthQuantB nan decode" in frames[1].error
    assert "says 16UC1, and its image holds float32 values" in frames[2].error
    reference = next(iter(open_bag(lab["bag"], "/tof/depth/image_raw"))).cloud.points
    for frame in frames[3:]:
        assert frame.error is None
        assert np.max(np.abs(np.sort(frame.cloud.points[:, 2]) - np.sort(reference[:, 2]))) < 6e-4


def test_a_camera_info_of_another_namespace_is_used_and_said(lab, tmp_path):
    millimetres = np.rint(np.nan_to_num(lab["grids"][0][..., 2]) * 1000).astype(np.uint16)
    messages = [
        ("/rgb/camera_info", INFO, _camera_info(ROS2, lab["camera"], ros1=False)),
        ("/cam/depth/image_raw", IMAGE, _image(ROS2, 0, millimetres)),
    ]
    bag = _write(tmp_path / "run", messages)
    said = r"no CameraInfo beside /cam/depth/image_raw; using /rgb/camera_info \(give --intr"
    with pytest.warns(SpaceposeWarning, match=said):
        open_bag(bag)


def test_a_zero_stamp_on_a_wall_clock_is_unset_and_a_left_out_topic_named(lab, tmp_path, capsys):
    """A frame stamped 0 among stamps of 1.7e9 s went to the trajectory at t = 0 without a
    word; a compressed colour topic left out was not said to be, nor why."""
    grid = lab["grids"][0][::8, ::8]
    messages = [("/points", PC2, _pointcloud2(ROS2, k, grid)) for k in range(3)]
    messages[0][2].header.stamp = ROS2.types["builtin_interfaces/msg/Time"](sec=0, nanosec=0)
    frames = list(open_bag(_write(tmp_path / "run", messages)))
    assert frames[0].error == "header stamp 0 on a clock that reads 1700000000 s: unset"
    assert [f.error for f in frames[1:]] == [None, None]
    jpeg = io.BytesIO()
    Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(jpeg, format="JPEG")
    colour = _compressed(ROS2, 0, "rgb8; jpeg compressed bgr8", jpeg.getvalue())
    bag = _write(tmp_path / "colour", [("/cam/color/compressed", COMPRESSED, colour)])
    assert main(["track", str(bag), "--out", str(tmp_path / "e.tum")]) == 1
    err = capsys.readouterr().err
    assert "; /cam/color/compressed left out: its first message's format 'rgb8; jpeg" in err, err


def test_a_damaged_camera_info_chunk_is_one_error_naming_the_bag(lab, tmp_path, capsys):
    """A ROS 1 bag of depth images whose CameraInfo sits in a damaged bz2 chunk: rosbags'
    reader raised OSError('Invalid data stream') out of the bag's opening, a traceback naming
    neither the bag nor the topic. Now one line names the bag."""
    camera = lab["camera"]
    path = tmp_path / "run.bag"
    writer = Writer1(path)
    writer.set_compression(Writer1.CompressionFormat.BZ2)
    writer.chunk_threshold = 1  # one message a chunk
    with writer:
        info = writer.add_connection("/cam/camera_info", INFO, typestore=ROS1)
        image = writer.add_connection("/cam/depth", IMAGE, typestore=ROS1)
        writer.write(info, 10**9, ROS1.serialize_ros1(_camera_info(ROS1, camera, True), INFO))
        for k in range(3):
            millimetres = np.full((camera.height, camera.width), 1200, dtype=np.uint16)
            msg = ROS1.serialize_ros1(_image(ROS1, k, millimetres), IMAGE)
            writer.write(image, 10**9 + (k + 1) * 10**8, msg)
    data = bytearray(path.read_bytes())
    first = next(i for i in range(len(data)) if data.startswith(b"BZh", i))
    data[first + 10 : first + 200] = bytes(190)
    path.write_bytes(bytes(data))
    with pytest.raises(FileFormatError, match="cannot read the bag's messages") as err:
        open_bag(path)
    assert str(path) in str(err.value)
    assert main(["track", str(path), "--out", str(tmp_path / "est.tum")]) == 1
    assert capsys.readouterr().err.strip().startswith(f"error: {path}: cannot read the bag's")
