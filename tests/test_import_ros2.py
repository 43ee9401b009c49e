"""`shiftkit import ros2`: rosbag2 recordings (sqlite3 and MCAP storage, written here with rosbags'
writer: real CDR serialisation) become LeRobot datasets through a mapping file, with documented
time alignment."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from shiftkit.app.cli import main
from shiftkit.app.importing import import_dataset
from shiftkit.datasets.errors import DatasetError
from shiftkit.datasets.importers.ros2 import _fetch, _plan, _scan, load_mapping
from shiftkit.datasets.importers.ros2 import _image as _image_of
from shiftkit.datasets.reader import open_lerobot_dataset

TS = get_typestore(Stores.ROS2_HUMBLE)
T0 = 1_700_000_000 * 10**9  # bag clock (ns)
JOINTS = ["joint1", "joint2", "joint3"]


def _header(t):
    return TS.types["std_msgs/msg/Header"](
        stamp=TS.types["builtin_interfaces/msg/Time"](sec=t // 10**9, nanosec=t % 10**9), frame_id="base"
    )


def _joint_state(t):
    q = np.array([1.0, 2.0, 3.0]) + (t - T0) / 1e9  # joint i reads i + seconds since T0
    return TS.types["sensor_msgs/msg/JointState"](
        header=_header(t), name=JOINTS, position=q, velocity=np.zeros(3), effort=np.zeros(0)
    )


def _image(t, encoding="rgb8"):
    k = (t - T0) // 10**8  # frame number at 10 Hz
    rgb = np.zeros((4, 5, 3), np.uint8)
    rgb[..., 0], rgb[..., 1], rgb[..., 2] = k, 100 + k, 200
    data = rgb[..., ::-1] if encoding == "bgr8" else rgb
    return TS.types["sensor_msgs/msg/Image"](
        header=_header(t), height=4, width=5, encoding=encoding, is_bigendian=0, step=15, data=data.reshape(-1).copy()
    )


def _twist(t):
    vec = TS.types["geometry_msgs/msg/Vector3"]
    s = (t - T0) / 1e9
    return TS.types["geometry_msgs/msg/Twist"](linear=vec(x=s, y=0.0, z=0.0), angular=vec(x=0.0, y=0.0, z=-s))


def _gripper(t):
    layout = TS.types["std_msgs/msg/MultiArrayLayout"](dim=[], data_offset=0)
    return TS.types["std_msgs/msg/Float64MultiArray"](layout=layout, data=np.array([(t - T0) / 1e9 > 0.5], float))


STREAMS = {  # topic: (type, period ns, first offset ns, message)
    "/joint_states": ("sensor_msgs/msg/JointState", 20_000_000, 0, _joint_state),  # 50 Hz
    "/camera/image_raw": ("sensor_msgs/msg/Image", 100_000_000, 30_000_000, _image),  # 10 Hz, starts last
    "/cmd_vel": ("geometry_msgs/msg/Twist", 50_000_000, 10_000_000, _twist),  # 20 Hz
    "/gripper": ("std_msgs/msg/Float64MultiArray", 100_000_000, 0, _gripper),
}


def _write_bag(
    path, duration_ns=1_000_000_000, storage=StoragePlugin.SQLITE3, markers=(), image_encoding="rgb8", streams=None
):
    """A bag of `streams` (default STREAMS; a test may swap one topic's message maker)."""
    streams = STREAMS if streams is None else streams
    with Writer(path, version=9, storage_plugin=storage) as writer:
        conns = {topic: writer.add_connection(topic, typ, typestore=TS) for topic, (typ, *_rest) in streams.items()}
        marker = writer.add_connection("/episode", "std_msgs/msg/Empty", typestore=TS) if markers else None
        events = []
        for topic, (typ, period, offset, make) in streams.items():
            for t in range(T0 + offset, T0 + duration_ns + 1, period):
                events.append((t, topic, typ, make))
        for t, topic, typ, make in sorted(events, key=lambda e: e[0]):
            msg = make(t, image_encoding) if make is _image else make(t)
            writer.write(conns[topic], t, TS.serialize_cdr(msg, typ))
        for t in markers:
            writer.write(marker, T0 + t, TS.serialize_cdr(TS.types["std_msgs/msg/Empty"](), "std_msgs/msg/Empty"))
    return path


MAPPING = """
fps = 10
align = "hold-last"
task = "wave"
robot_type = "test_arm"
[[features."observation.state"]]
topic = "/joint_states"
field = "position"
[[features."observation.state"]]
topic = "/gripper"
field = "data"
names = ["gripper"]
[features."observation.images.front"]
topic = "/camera/image_raw"
[[features.action]]
topic = "/cmd_vel"
field = "linear.x"
[[features.action]]
topic = "/cmd_vel"
field = "angular.z"
"""


def _tree_digest(path):
    return hashlib.sha256(b"".join(p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file())).hexdigest()


def test_bag_imports_with_hold_last_alignment(tmp_path, capsys):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    bag = _write_bag(tmp_path / "rec1")
    mapping = tmp_path / "mapping.toml"
    mapping.write_text(MAPPING)
    digest = _tree_digest(bag)
    assert (
        main(["import", "ros2", str(bag), "--mapping", str(mapping), "--repo-id", "r/b", "--root", str(tmp_path / "o")])
        == 0
    )
    assert "rec1: 1 episode(s), lengths [10]" in capsys.readouterr().out
    assert _tree_digest(bag) == digest

    ds = LeRobotDataset("r/b", root=tmp_path / "o")
    assert ds.fps == 10 and ds.num_episodes == 1 and ds.meta.robot_type == "test_arm"
    assert ds.features["observation.state"]["names"] == [*(f"{j}.position" for j in JOINTS), "gripper"]
    assert ds.features["action"]["names"] == ["cmd_vel.linear.x", "cmd_vel.angular.z"]
    (ep,) = open_lerobot_dataset(tmp_path / "o").iter_episodes()
    # Frames start when the last topic (the camera, +30 ms) first publishes: t_k = 0.03 + k/10 s, and
    # end at the earliest last message (camera at 0.93 s). hold-last: latest message at or before t_k.
    t = 0.03 + np.arange(10) / 10
    joint_t = np.floor(t * 50 + 1e-9) / 50  # 50 Hz from 0
    np.testing.assert_allclose(ep.frames["observation.state"][:, :3], joint_t[:, None] + [1, 2, 3], atol=1e-6)
    np.testing.assert_array_equal(ep.frames["observation.state"][:, 3], (np.floor(t * 10) / 10 > 0.5))
    cmd_t = np.floor((t - 0.01) * 20 + 1e-9) / 20 + 0.01  # 20 Hz from 10 ms
    np.testing.assert_allclose(ep.frames["action"], np.stack([cmd_t, -cmd_t], axis=1), atol=1e-6)
    np.testing.assert_array_equal(
        ep.frames["observation.images.front"][:, 0, 0], [[k, 100 + k, 200] for k in range(10)]
    )
    assert ep.meta["source"] == {"bag": "rec1", "start_ns": T0 + 30_000_000, "segment": 0}

    # Only the messages a frame takes are deserialised and kept (51 joint states at 50 Hz -> 10 frames).
    m = load_mapping(mapping)
    index = _scan(bag, m)
    fetched = _fetch(bag, m, _plan(bag, m, index, 10))
    assert len(index.times["/joint_states"]) == 51 and len(fetched["/joint_states"]) == 10


def test_mcap_nearest_alignment_and_split_topic(tmp_path):
    bag = _write_bag(tmp_path / "rec2", storage=StoragePlugin.MCAP, markers=(0, 500_000_000), image_encoding="bgr8")
    mcap_file = next(bag.glob("*.mcap"))
    mapping = tmp_path / "mapping.yaml"
    mapping.write_text(
        "fps: 20\nalign: nearest\ntask: wave\nsplit_topic: /episode\nfeatures:\n"
        "  observation.state: {topic: /joint_states, field: position, indices: [2]}\n"
        "  observation.images.front: {topic: /camera/image_raw}\n"
        "  action: {topic: /cmd_vel, field: linear.x}\n"
    )
    digest = hashlib.sha256(mcap_file.read_bytes()).hexdigest()
    options = {"bags": [str(mcap_file)], "mapping": str(mapping)}
    dataset = import_dataset("ros2", options, "r/m", tmp_path / "o")  # a bare .mcap file, no metadata.yaml
    assert hashlib.sha256(mcap_file.read_bytes()).hexdigest() == digest
    assert dataset.provenance["sources"][0]["bags"][0]["lengths"] == [9, 9] and dataset.fps == 20
    first, second = open_lerobot_dataset(tmp_path / "o").iter_episodes()
    # episode 1: [0, 0.5 s) -> start 0.03 (camera), end 0.43 (camera's last in the segment); nearest message
    t = 0.03 + np.arange(9) / 20
    np.testing.assert_allclose(
        first.frames["observation.state"][:, 0], 3 + np.ceil(t * 50 - 0.5 - 1e-9) / 50, atol=1e-6
    )
    # ties (a frame exactly between two messages) take the earlier message
    cmd = np.ceil((t - 0.01) * 20 - 0.5 - 1e-9) / 20 + 0.01
    np.testing.assert_allclose(first.frames["action"][:, 0], cmd, atol=1e-6)
    assert first.frames["observation.images.front"][0, 0, 0].tolist() == [0, 100, 200]  # bgr8 -> RGB
    assert second.meta["source"]["start_ns"] == T0 + 530_000_000
    info = json.loads((tmp_path / "o" / "meta" / "info.json").read_text())
    assert info["features"]["observation.state"]["names"] == ["joint3.position"]


@pytest.mark.parametrize(
    ("mapping", "message"),
    [
        ('fps = 10\ntask = "x"\n[features.action]\ntopic = "/cmd_vell"\nfield = "linear.x"\n', "no topic '/cmd_vell'"),
        ('fps = 10\ntask = "x"\n[features.action]\ntopic = "/cmd_vel"\nfield = "linear.w"\n', "has no field 'w'"),
        ('fps = 10\ntask = "x"\n[features.action]\ntopic = "/joint_states"\nfield = "name"\n', "is not numeric"),
        ('fps = 10\ntask = "x"\n[features."observation.images.a"]\ntopic = "/cmd_vel"\n', "not an image"),
        ('fps = 10\ntask = "x"\nfeature = 1\n', "unknown key 'feature'"),
        ('fps = 10\ntask = "x"\nfeatures = {}\n', "map at least one feature"),
        ('task = "x"\n[features.action]\ntopic = "/cmd_vel"\nfield = "linear.x"\n', "give a positive fps"),
        (
            'fps = 10\ntask = "x"\nalign = "linear"\n[features.action]\ntopic = "/cmd_vel"\nfield = "linear.x"\n',
            "align",
        ),
    ],
)
def test_bad_mappings_are_one_line_errors(tmp_path, capsys, mapping, message):
    bag = _write_bag(tmp_path / "rec", duration_ns=200_000_000)
    path = tmp_path / "m.toml"
    path.write_text(mapping)
    digest = _tree_digest(bag)
    assert (
        main(["import", "ros2", str(bag), "--mapping", str(path), "--repo-id", "a/b", "--root", str(tmp_path / "o")])
        == 2
    )
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err and "Traceback" not in err, err
    assert not (tmp_path / "o").exists() and _tree_digest(bag) == digest


def test_bad_bags_are_one_line_errors(tmp_path, capsys):
    mapping = tmp_path / "m.toml"
    mapping.write_text(MAPPING)
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file")
    for bag, message in ((junk, "cannot read the bag"), (tmp_path / "missing", "cannot read the bag")):
        assert (
            main(
                [
                    "import",
                    "ros2",
                    str(bag),
                    "--mapping",
                    str(mapping),
                    "--repo-id",
                    "a/b",
                    "--root",
                    str(tmp_path / "o"),
                ]
            )
            == 2
        )
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and message in err and "Traceback" not in err, err
    assert junk.read_bytes() == b"not an mcap file" and not (tmp_path / "o").exists()


def _write_mcap_ros2(path, latency_ns):
    """An MCAP file from the other maintained writer (mcap-ros2-support: ros2msg schemas, its own CDR
    encoder); the camera is received `latency_ns` after its header stamp."""
    from mcap_ros2.writer import Writer as McapWriter

    with path.open("wb") as f:
        writer = McapWriter(f)
        schemas = {
            typ: writer.register_msgdef(typ, TS.generate_msgdef(typ, ros_version=2)[0])
            for typ in ("sensor_msgs/msg/JointState", "sensor_msgs/msg/Image")
        }
        events = [(t, "/joint_states") for t in range(T0, T0 + 10**9 + 1, 20_000_000)]
        events += [(t, "/camera/image_raw") for t in range(T0 + 30_000_000, T0 + 10**9 + 1, 100_000_000)]
        for stamp, topic in sorted(events, key=lambda e: e[0] + (latency_ns if e[1] == "/camera/image_raw" else 0)):
            header = {"stamp": {"sec": stamp // 10**9, "nanosec": stamp % 10**9}, "frame_id": "base"}
            if topic == "/joint_states":
                q = (np.array([1.0, 2.0, 3.0]) + (stamp - T0) / 1e9).tolist()
                typ, msg, received = (
                    "sensor_msgs/msg/JointState",
                    {"header": header, "name": JOINTS, "position": q},
                    stamp,
                )
            else:
                img = _image(stamp)
                typ, received = "sensor_msgs/msg/Image", stamp + latency_ns
                msg = {"header": header, "height": 4, "width": 5, "encoding": "rgb8", "is_bigendian": 0, "step": 15}
                msg["data"] = img.data.tobytes()
            writer.write_message(topic, schemas[typ], msg, log_time=received, publish_time=received)
        writer.finish()
    return path


def test_header_stamps_align_sensor_time(tmp_path):
    mcap_file = _write_mcap_ros2(tmp_path / "cam_latency.mcap", latency_ns=45_000_000)
    base = (
        'fps = 10\ntask = "x"\n[features."observation.state"]\ntopic = "/joint_states"\nfield = "position"\n'
        '[features."observation.images.front"]\ntopic = "/camera/image_raw"\n'
    )
    results = {}
    for time in ("receive", "header"):
        mapping = tmp_path / f"{time}.toml"
        mapping.write_text(f'time = "{time}"\n' + base)
        import_dataset("ros2", {"bags": [str(mcap_file)], "mapping": str(mapping)}, "r/t", tmp_path / time)
        (results[time],) = open_lerobot_dataset(tmp_path / time).iter_episodes()
    # receive time: the camera arrives 45 ms late, so frames start at 75 ms and pair image k with joints
    # read 45 ms after it was taken; header time: frames start at the image stamp (30 ms), joints from then.
    assert results["receive"].meta["source"]["start_ns"] == T0 + 75_000_000
    assert results["header"].meta["source"]["start_ns"] == T0 + 30_000_000
    for ep, start in ((results["receive"], 0.075), (results["header"], 0.03)):
        t = start + np.arange(len(ep)) / 10
        np.testing.assert_allclose(ep.frames["observation.state"][:, 0], 1 + np.floor(t * 50 + 1e-9) / 50, atol=1e-6)
    header = results["header"].frames["observation.images.front"][:, 0, 0, 0]
    np.testing.assert_array_equal(header, np.arange(len(header)))  # image k at frame k (its stamp)

    mapping = tmp_path / "bad.toml"
    mapping.write_text(
        'time = "header"\nfps = 10\ntask = "x"\n[features.action]\ntopic = "/cmd_vel"\nfield = "linear.x"\n'
    )
    bag = _write_bag(tmp_path / "rec", duration_ns=200_000_000)
    with pytest.raises(DatasetError, match=r"/cmd_vel \(geometry_msgs/msg/Twist\) has no header.stamp"):
        import_dataset("ros2", {"bags": [str(bag)], "mapping": str(mapping)}, "r/t", tmp_path / "bad")


def test_image_encodings():
    """Row padding (step > width * channels), mono8 and CompressedImage (PNG) all come out as RGB (H, W, 3)."""
    import cv2

    rgb = np.arange(4 * 5 * 3, dtype=np.uint8).reshape(4, 5, 3)
    padded = np.zeros((4, 16), np.uint8)
    padded[:, :15] = rgb[..., ::-1].reshape(4, 15)  # bgr8 rows padded to 16 bytes
    image = TS.types["sensor_msgs/msg/Image"]
    msg = image(
        header=_header(T0), height=4, width=5, encoding="bgr8", is_bigendian=0, step=16, data=padded.reshape(-1)
    )
    np.testing.assert_array_equal(_image_of(msg, "t"), rgb)
    mono = rgb[..., 0].copy()
    msg = image(header=_header(T0), height=4, width=5, encoding="mono8", is_bigendian=0, step=5, data=mono.reshape(-1))
    np.testing.assert_array_equal(_image_of(msg, "t"), np.repeat(mono[..., None], 3, axis=2))
    png = np.frombuffer(cv2.imencode(".png", rgb[..., ::-1])[1].tobytes(), np.uint8)
    compressed = TS.types["sensor_msgs/msg/CompressedImage"](header=_header(T0), format="png", data=png)
    np.testing.assert_array_equal(_image_of(compressed, "t"), rgb)
    msg = image(
        header=_header(T0), height=4, width=5, encoding="16UC1", is_bigendian=0, step=10, data=padded.reshape(-1)
    )
    with pytest.raises(DatasetError, match="encoding '16UC1' is not supported"):
        _image_of(msg, "t")
