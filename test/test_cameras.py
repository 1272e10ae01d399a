"""Camera backends without hardware: factory, RealSense options/deprojection/fail-fast, bag replay."""

import itertools
import time

import numpy as np
import pytest

from equidiff_core.cameras import (
    BACKENDS,
    CameraError,
    CloudFrame,
    limit_depth,
    make_camera,
)
from equidiff_core.cameras.realsense import RealSenseOptions, depth_to_cloud, pixel_rays
from equidiff_core.cameras.replay import ReplayFinished
from equidiff_core.config import (
    CameraConfig,
    Extrinsics,
    default_config_dir,
    load_lab_config,
)
from equidiff_core.wire.pointcloud import cloud_to_msg
from equidiff_core.wire.rosmsg import rosbags_factory


def _camera(name="cam_a", **kw):
    return CameraConfig(name=name, serial="000000000042", extrinsics=Extrinsics((0, 0, 1), (0, 0, 0, 1)), **kw)


def test_factory_rejects_unknown_backend_and_lists_the_known_ones():
    with pytest.raises(CameraError, match=r"unknown camera backend 'kinect'.*realsense.*replay.*twin"):
        make_camera("kinect", _camera())
    assert set(BACKENDS) == {"realsense", "replay", "twin"}


def test_realsense_without_device_fails_fast_naming_the_serial():
    cam = make_camera("realsense", _camera())
    t0 = time.monotonic()
    with pytest.raises(CameraError, match=r"'cam_a' with serial 000000000042 not found"):
        cam.connect()
    assert time.monotonic() - t0 < 5.0
    assert not cam.is_connected
    with pytest.raises(CameraError, match="not connected"):
        cam.read()
    cam.disconnect()  # safe without a connection


def test_realsense_options_come_from_lab_yaml_and_bad_ones_name_the_camera():
    lab = load_lab_config(default_config_dir() / "lab.yaml")
    cam = make_camera("realsense", lab.cameras[0])
    assert cam.options == RealSenseOptions(
        decimation=2, spatial=True, temporal=True, hole_filling=False, exposure_us=8500, white_balance_k=4600
    )
    with pytest.raises(
        CameraError, match=r"cameras\[cam_a\]\.options\.decimation: 9 is out of range; allowed: 1 <= x <= 8"
    ):
        make_camera("realsense", _camera(options={"decimation": 9}))
    with pytest.raises(CameraError, match=r"unknown key\(s\) \['exposure'\]"):
        make_camera("realsense", _camera(options={"exposure": 100}))
    with pytest.raises(CameraError, match="visual_preset"):
        make_camera("realsense", _camera(), visual_preset="sharpest")


def test_depth_image_deprojects_to_the_expected_points_and_colours():
    w, h, fx, fy, ppx, ppy = 8, 6, 4.0, 5.0, 3.5, 2.5
    rays = pixel_rays(w, h, fx, fy, ppx, ppy)
    # the closed form equals a per-pixel deprojection callback (the distortion path)
    np.testing.assert_allclose(
        pixel_rays(w, h, fx, fy, ppx, ppy, lambda u, v: ((u - ppx) / fx, (v - ppy) / fy)), rays, rtol=0, atol=1e-6
    )
    depth = np.zeros((h, w), np.uint16)
    depth[0, 0] = 1000  # 1 m at scale 1 mm
    depth[5, 7] = 2500  # 2.5 m: beyond max_depth below
    depth[2, 3] = 500
    color = np.zeros((h, w, 3), np.uint8)
    color[0, 0] = (10, 20, 30)
    color[2, 3] = (1, 2, 3)
    pts, cols = depth_to_cloud(depth, 0.001, color, rays, min_depth=0.1, max_depth=2.0)
    np.testing.assert_allclose(
        pts,
        [[(0 - 3.5) / 4 * 1.0, (0 - 2.5) / 5 * 1.0, 1.0], [(3 - 3.5) / 4 * 0.5, (2 - 2.5) / 5 * 0.5, 0.5]],
        atol=1e-6,
    )
    np.testing.assert_array_equal(cols, [[10, 20, 30], [1, 2, 3]])
    with pytest.raises(CameraError, match="disagree"):
        depth_to_cloud(depth[:5], 0.001, color, rays, 0.1, 2.0)


def test_limit_depth_drops_points_outside_the_range_and_nan():
    pts = np.array([[0, 0, 0.05], [0, 0, 0.5], [0, 0, 3.0], [0, 0, np.nan]], np.float32)
    frame = CloudFrame(pts, np.arange(12, dtype=np.uint8).reshape(4, 3), 7)
    out = limit_depth(frame, 0.1, 2.0)
    np.testing.assert_array_equal(out.points, pts[1:2])
    np.testing.assert_array_equal(out.colors, [[3, 4, 5]])
    assert out.stamp_ns == 7


def write_cloud_bag(path, clouds_by_topic, period_ns=100_000_000, start_ns=1_700_000_000_000_000_000):
    """A rosbag2 (MCAP) directory with PointCloud2 messages; returns the written stamps per topic."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    f = rosbags_factory()
    ts = f.typestore
    stamps = {}
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        for topic, clouds in clouds_by_topic.items():
            conn = writer.add_connection(topic, "sensor_msgs/msg/PointCloud2", typestore=ts)
            stamps[topic] = []
            for i, (pts, cols) in enumerate(clouds):
                stamp = start_ns + i * period_ns
                frame = topic.split("/")[2] + "_color_optical_frame"
                msg = cloud_to_msg(pts, cols, stamp, frame, f)
                writer.write(conn, stamp, ts.serialize_cdr(msg, "sensor_msgs/msg/PointCloud2"))
                stamps[topic].append(stamp)
    return stamps


def _clouds(n, seed=0, size=50):
    rng = np.random.default_rng(seed)
    return [
        (rng.normal(size=(size, 3)).astype(np.float32), rng.integers(0, 256, (size, 3), dtype=np.uint8))
        for _ in range(n)
    ]


def _frame_index(frame, clouds):
    matches = [i for i, (p, _) in enumerate(clouds) if len(p) == len(frame.points) and np.array_equal(p, frame.points)]
    return matches[0] if matches else None


def test_replay_plays_a_bag_at_the_recorded_pace_restamped_and_loops(tmp_path):
    clouds = _clouds(3)
    clouds[1] = (clouds[1][0].copy(), clouds[1][1])
    clouds[1][0][0] = np.nan  # a NaN point in a recorded frame is dropped, not fatal
    bag = tmp_path / "bag"
    recorded = write_cloud_bag(bag, {"/cameras/cam_a/points": clouds, "/cameras/cam_b/points": _clouds(3, 1)})
    offset = 10**12  # a clock that is not the wall clock: stamps come from it

    cam = make_camera("replay", _camera(), bag=str(bag), clock=lambda: time.time_ns() + offset)
    with cam:
        t0 = time.monotonic()
        frames = [cam.read(timeout_s=1.0) for _ in range(5)]
        elapsed = time.monotonic() - t0
    # 0.1 s between frames, 0.2 s (one 5 Hz period) from the last frame back to the first
    assert 0.3 < elapsed < 2.0
    first = _frame_index(frames[0], clouds) if len(frames[0].points) == 50 else 1
    for i, frame in enumerate(frames):
        k = (first + i) % 3
        if k == 1:
            assert len(frame.points) == 49  # the NaN point is gone
        else:
            np.testing.assert_array_equal(frame.points, clouds[k][0])
            np.testing.assert_array_equal(frame.colors, clouds[k][1])
        assert abs(frame.stamp_ns - offset - time.time_ns()) < 3e9  # restamped by the given clock
    assert all(b.stamp_ns > a.stamp_ns for a, b in itertools.pairwise(frames))
    with make_camera("replay", _camera("cam_b"), bag=str(bag), restamp=False, loop=False, rate=4.0) as cam_b:
        assert [cam_b.read().stamp_ns for _ in range(3)] == recorded["/cameras/cam_b/points"]
        with pytest.raises(ReplayFinished, match="finished after 3 frames"):
            cam_b.read()


def test_replays_in_separate_processes_deliver_the_same_instant_together(tmp_path):
    import threading

    clouds = _clouds(6, seed=3)
    bag = tmp_path / "bag"
    write_cloud_bag(bag, {"/cameras/cam_a/points": clouds}, period_ns=200_000_000)
    delivered = {}

    def play(key, delay):
        time.sleep(delay)
        with make_camera("replay", _camera(), bag=str(bag)) as cam:
            delivered[key] = [(_frame_index(f, clouds), time.monotonic()) for f in (cam.read() for _ in range(4))]

    threads = [threading.Thread(target=play, args=(key, delay)) for key, delay in (("a", 0.0), ("b", 0.33))]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=10)
    by_index_a = {i: t for i, t in delivered["a"]}
    common = [(i, t) for i, t in delivered["b"] if i in by_index_a]
    assert common, (delivered["a"], delivered["b"])  # b joined while a was still playing
    for i, t in common:
        assert abs(t - by_index_a[i]) < 0.08  # the same recorded frame at the same moment


def test_replay_errors_name_the_bag_and_topic(tmp_path):
    bag = tmp_path / "bag"
    write_cloud_bag(bag, {"/cameras/cam_a/points": _clouds(1)})
    with pytest.raises(
        CameraError,
        match=r"no messages on /cameras/cam_z/points; its PointCloud2 topics: "
        r"\['/cameras/cam_a/points'\]",
    ):
        make_camera("replay", _camera("cam_z"), bag=str(bag)).connect()
    with pytest.raises(CameraError, match="not a rosbag2 directory"):
        make_camera("replay", _camera(), bag=str(tmp_path / "nowhere")).connect()
    with pytest.raises(CameraError, match="no bag given"):
        make_camera("replay", _camera())
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "metadata.yaml").write_text("rosbag2_bagfile_information: {version: 9, garbage")
    with pytest.raises(CameraError, match="cannot open"):
        make_camera("replay", _camera(), bag=str(broken)).connect()


def test_twin_backend_is_reached_through_the_factory():
    pytest.importorskip("mujoco")
    with pytest.raises(CameraError, match="unknown option"):
        make_camera("twin", _camera(), no_such_option=1)


def test_extrinsics_tf_message_carries_each_optical_frame():
    from equidiff_core import geometry
    from equidiff_core.cameras import extrinsics_tf_message

    lab = load_lab_config(default_config_dir() / "lab.yaml")
    f = rosbags_factory()
    msg = extrinsics_tf_message(lab.cameras, lab.base_frame, 123, f)
    msg = f.typestore.deserialize_cdr(
        f.typestore.serialize_cdr(msg, "tf2_msgs/msg/TFMessage"), "tf2_msgs/msg/TFMessage"
    )
    assert [t.child_frame_id for t in msg.transforms] == [c.frame_id for c in lab.cameras]
    for t, cam in zip(msg.transforms, lab.cameras):
        assert t.header.frame_id == "fr3_link0" and t.header.stamp.nanosec == 123
        tr, r = t.transform.translation, t.transform.rotation
        T = geometry.pose_from_pos_quat([tr.x, tr.y, tr.z], [r.x, r.y, r.z, r.w])
        np.testing.assert_allclose(T, cam.extrinsics.matrix(), atol=1e-9)


class _FakeRealSense:
    """Just enough of pyrealsense2's frame objects to drive RealSenseCamera.read without a device."""

    def __init__(self, depth, color, fx=4.0, ppx=3.5, ppy=2.5, global_time=True, fps=30.0):
        from types import SimpleNamespace as NS

        self.rs = NS(timestamp_domain=NS(global_time="global", system_time="system"), distortion=NS(none="none"))
        self.depth, self.color, self.fps, self.global_time = depth, color, fps, global_time
        self.intr = NS(
            width=depth.shape[1], height=depth.shape[0], fx=fx, fy=fx, ppx=ppx, ppy=ppy, coeffs=[0.0] * 5, model="none"
        )
        self.served = 0
        self.fail = False

    def frame(self, data, intr):
        from types import SimpleNamespace as NS

        profile = NS(as_video_stream_profile=lambda: NS(get_intrinsics=lambda: intr))
        return NS(get_data=lambda: data, profile=profile)

    def wait_for_frames(self, timeout_ms):
        from types import SimpleNamespace as NS

        if self.fail:
            raise RuntimeError("Frame didn't arrive within 1000")
        time.sleep(1.0 / self.fps)
        self.served += 1
        depth, color = self.frame(self.depth, self.intr), self.frame(self.color, None)
        return NS(
            get_depth_frame=lambda: depth,
            get_color_frame=lambda: color,
            get_timestamp=lambda: 1_700_000_000_123.5,
            get_frame_timestamp_domain=lambda: "global" if self.global_time else "system",
        )

    def attach(self, cam, filters=()):
        from types import SimpleNamespace as NS

        cam._rs, cam._pipeline, cam._filters, cam._depth_scale = self.rs, self, list(filters), 0.001
        cam._opened = True
        cam._align = NS(process=self.process)
        self.processed = 0

    def process(self, frames):
        self.processed += 1
        return frames

    def stop(self):
        pass


def test_realsense_read_deprojects_stamps_and_samples_colour_after_decimation():
    from types import SimpleNamespace as NS

    from equidiff_core.cameras.realsense import RealSenseCamera

    depth = np.zeros((6, 8), np.uint16)
    depth[2, 3] = 500
    depth[5, 7] = 2500  # beyond max_depth
    color = np.zeros((6, 8, 3), np.uint8)
    color[2, 3] = (1, 2, 3)
    fake = _FakeRealSense(depth, color)
    cam = RealSenseCamera(_camera(max_depth=2.0), clock=lambda: 42)
    fake.attach(cam)
    frame = cam.read()
    np.testing.assert_allclose(frame.points, [[(3 - 3.5) / 4 * 0.5, (2 - 2.5) / 4 * 0.5, 0.5]], atol=1e-6)
    np.testing.assert_array_equal(frame.colors, [[1, 2, 3]])
    np.testing.assert_array_equal(frame.image, color)  # the whole colour image travels with the cloud
    assert frame.image is not color  # a copy: librealsense reuses the frame's buffer
    assert frame.stamp_ns == 1_700_000_000_123_500_000  # global time: the capture time on the host clock
    fake.global_time = False
    assert cam.read().stamp_ns == 42  # other domains: arrival time on the node's clock

    # a decimation-like filter halves the depth image: colour is sampled at each pixel's centre
    half = NS(width=4, height=3, fx=2.0, fy=2.0, ppx=1.75, ppy=1.25, coeffs=[0.0] * 5, model="none")
    small = np.zeros((3, 4), np.uint16)
    small[1, 1] = 1000
    color[3, 3] = (9, 8, 7)  # (1, 1) * 2 + 1
    decimate = NS(process=lambda f: fake.frame(small, half))
    fake.attach(cam, [decimate])
    frame = cam.read()
    np.testing.assert_allclose(frame.points, [[(1 - 1.75) / 2, (1 - 1.25) / 2, 1.0]], atol=1e-6)
    np.testing.assert_array_equal(frame.colors, [[9, 8, 7]])
    assert frame.image.shape == (6, 8, 3)  # full resolution, not decimated like the depth

    fake.fail = True
    with pytest.raises(CameraError, match="serial 000000000042|000000000042.*no frame within"):
        cam.read(timeout_s=0.1)


def test_realsense_processes_only_the_frames_it_will_publish():
    from equidiff_core.cameras.realsense import RealSenseCamera

    depth = np.full((6, 8), 800, np.uint16)
    fake = _FakeRealSense(depth, np.zeros((6, 8, 3), np.uint8), fps=30.0)
    cam = RealSenseCamera(_camera(), pace_hz=5.0)
    fake.attach(cam)
    cam.read()
    served, t0 = fake.served, time.monotonic()
    for _ in range(3):
        cam.read()
    elapsed = time.monotonic() - t0
    # Frames are phase-locked to the 0.2 s grid with a quarter period of tolerance and the first
    # read lands at any phase, so three more take at least two periods minus the tolerance.
    assert 0.34 < elapsed < 2.0
    assert fake.processed == 4  # only the published frames are aligned and deprojected...
    assert fake.served - served >= 6  # ...while the device's other frames are fetched and dropped


def test_colour_image_travels_as_image_transport_jpeg_and_bad_ones_are_refused():
    from equidiff_core.cameras.color import (
        JPEG_FORMAT,
        ImageError,
        color_image_msg,
        compressed_format,
        encode_jpeg,
        image_from_msg,
    )
    from equidiff_core.wire.rosmsg import rosbags_factory

    f = rosbags_factory()
    v, u = np.mgrid[0:120, 0:212]
    rgb = np.stack([u, v * 2, 255 - u], axis=-1).astype(np.uint8)  # smooth: JPEG keeps it within a few levels
    rgb[40:80, 90:130] = (200, 30, 30)  # and a flat block with edges
    msg = color_image_msg(rgb, 1_700_000_000_123_456_789, "cam_front_color_optical_frame", f, quality=90)
    assert msg.format == JPEG_FORMAT == "rgb8; jpeg compressed bgr8"  # compressed_image_transport's string
    assert msg.header.frame_id == "cam_front_color_optical_frame"
    raw = f.typestore.serialize_cdr(msg, "sensor_msgs/msg/CompressedImage")
    back, stamp = image_from_msg(f.typestore.deserialize_cdr(raw, "sensor_msgs/msg/CompressedImage"))
    assert stamp == 1_700_000_000_123_456_789 and back.shape == rgb.shape
    assert np.abs(back.astype(int) - rgb).mean() < 2.0
    np.testing.assert_array_equal(back[60, 110], rgb[60, 110])  # colour order kept (RGB in, RGB out)
    assert len(raw) < rgb.nbytes / 10

    for fmt, kind in (("jpeg", "jpeg"), ("bgr8; png compressed bgr8", "png"), ("JPG", "jpeg")):
        assert (
            compressed_format(f.make("sensor_msgs/msg/CompressedImage", header=msg.header, format=fmt, data=msg.data))
            == kind
        )
    for bad in (np.zeros((4, 4), np.uint8), np.zeros((4, 4, 3), np.float32), np.zeros((0, 4, 3), np.uint8)):
        with pytest.raises(ImageError, match="RGB uint8"):
            encode_jpeg(bad)
    with pytest.raises(ImageError, match="quality"):
        encode_jpeg(rgb, quality=0)
    garbage = f.make(
        "sensor_msgs/msg/CompressedImage", header=msg.header, format=JPEG_FORMAT, data=np.arange(50, dtype=np.uint8)
    )
    with pytest.raises(ImageError, match="undecodable"):
        image_from_msg(garbage)
    with pytest.raises(ImageError, match="unsupported"):
        image_from_msg(f.make("sensor_msgs/msg/CompressedImage", header=msg.header, format="theora", data=msg.data))


def test_limit_depth_keeps_the_colour_image():
    image = np.full((2, 2, 3), 7, np.uint8)
    frame = CloudFrame(np.array([[0, 0, 0.5], [0, 0, 9.0]], np.float32), np.zeros((2, 3), np.uint8), 5, image)
    assert limit_depth(frame, 0.1, 2.0).image is image


@pytest.mark.sim
def test_image_cost_bench_measures_each_size_against_its_baselines():
    from equidiff_core.benches.images import measure
    from equidiff_core.config import default_config_dir, load_lab_config
    from equidiff_core.twin.config import TwinConfig

    twin = TwinConfig()
    result = measure(load_lab_config(default_config_dir() / "lab.yaml"), twin, repeats=2)
    cases = result["cases"]
    twin_size = f"twin_{twin.render.width}x{twin.render.height}"
    assert set(cases) == {twin_size, "lab_848x480", "lab_848x480_noise2_estimate"}
    for case in cases.values():
        assert 0 < case["jpeg_kb_per_frame"] < case["raw_rgb_kb_per_frame"] / 4  # JPEG, not raw pixels
        assert case["camera_node_jpeg_cpu_ms"] > 0 and case["recorder_write_image_cpu_ms"] > 0
        assert case["images_mb_per_min"] == pytest.approx(case["jpeg_kb_per_frame"] * 3 * 5 * 60 / 1e3, rel=0.01)
    assert cases["lab_848x480"]["width"] == 848 and cases["lab_848x480"]["height"] == 480  # beyond MuJoCo's 640 default
    assert cases["lab_848x480_noise2_estimate"]["jpeg_kb_per_frame"] > cases["lab_848x480"]["jpeg_kb_per_frame"]
