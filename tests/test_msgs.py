"""Typed messages and their msgpack codec: round trips, zero copy, rejection of malformed input."""

import msgpack
import numpy as np
import pytest

import msgs
from msgs import MESSAGE_TYPES, TOPIC_TYPES, Header, MessageError, decode, decode_frames, encode, encode_frames
from twinfocus.errors import TwinFocusError
from twinfocus.radar.fmcw import Chirp, mmwcas_virtual_array

RNG = np.random.default_rng(7)


def flat_2x2():
    """A TwinTemplate's fields for a 2 x 2 float32 image at 1 m."""
    return {"image": np.zeros((2, 2), np.float32), "x_m": np.zeros(2), "y_m": np.zeros(2), "z_m": 1}


def cplx(*shape):
    return (RNG.standard_normal(shape) + 1j * RNG.standard_normal(shape)).astype(np.complex64)


def one_of_each():
    """A realistic instance of every message type (MMWCAS-sized radar data)."""
    k, n = 86, 256
    offsets = mmwcas_virtual_array().offsets_m
    c = Chirp()
    return [
        msgs.RadarFrame(
            header=Header(1_000, 3, "radar"),
            data=cplx(k, n),
            f0_hz=c.f0_hz,
            slope_hz_per_s=c.slope_hz_per_s,
            fs_hz=c.fs_hz,
            channel_offsets_m=offsets,
            scan_id="s1",
            index=5,
            last=False,
            positions_true_m=RNG.standard_normal((k, 3)),
        ),
        msgs.Pose(
            header=Header(2_000, 0, "scene"),
            position_m=np.array([0.1, -0.2, 0.003]),
            quat_xyzw=np.array([0.0, 0.0, np.sin(0.1), np.cos(0.1)]),
            confidence=0.9,
            child_frame_id="camera",
        ),
        msgs.StereoFrame(
            header=Header(3, 1, "camera"),
            left=RNG.integers(0, 255, (48, 64, 3), dtype=np.uint8),
            right=RNG.integers(0, 255, (48, 64, 3), dtype=np.uint8),
            camera_matrix=np.eye(3) * 500,
            baseline_m=0.12,
            depth_m=RNG.random((48, 64)).astype(np.float32),
        ),
        msgs.SarMeasurement(
            header=Header(4, 2, "scene"),
            data=cplx(k, n),
            positions_m=RNG.standard_normal((k, 3)),
            f0_hz=c.f0_hz,
            slope_hz_per_s=c.slope_hz_per_s,
            fs_hz=c.fs_hz,
            scan_id="s1",
            index=7,
            last=True,
            pose_gap_ns=33_333_333,
        ),
        msgs.TwinTemplate(
            header=Header(5, 0, "scene"),
            image=RNG.random((30, 40)).astype(np.float32),
            x_m=np.linspace(-0.15, 0, 40),
            y_m=np.linspace(-0.11, 0.12, 30),
            z_m=0.6,
            kind="physical",
            source="stage.npz",
            phase_rad=RNG.uniform(-3, 3, (30, 40)).astype(np.float32),
            support=RNG.random((30, 40)) > 0.5,
        ),
        msgs.AutofocusResult(
            header=Header(6, 0, "scene"),
            scan_id="s1",
            method="twin",
            phase_rad=RNG.standard_normal(780),
            loss_history=RNG.random(300),
            metrics={"ssim": 0.9, "n": 3.0},
            timing_s={"autofocus": 1.5},
            estimator="outline",
        ),
        msgs.Image(
            header=Header(7, 0, "scene"),
            name="target",
            scan_id="s1",
            image=cplx(100, 100),
            x_m=np.linspace(0.02, 0.13, 100),
            y_m=np.linspace(-0.11, 0.12, 100),
            z_m=0.6,
        ),
        msgs.NodeStatus(
            header=Header(8, 9, ""),
            node="solver",
            state="running",
            pid=123,
            publishes=["a/b"],
            subscribes=["c/d", "*"],
            types={"a/b": "Image"},
            received={"c/d": 4},
            published={"a/b": 1},
            lost={"c/d": 2},
            message="ok",
        ),
    ]


def assert_same(a, b):
    assert type(a) is type(b)
    assert a.header == b.header
    for name in a.__dataclass_fields__:
        x, y = getattr(a, name), getattr(b, name)
        if isinstance(x, np.ndarray):
            assert y.dtype == x.dtype and y.shape == x.shape
            assert x.tobytes() == y.tobytes(), name  # bit-exact
        else:
            assert x == y, name


def test_every_topic_kind_has_a_type_and_the_instances_cover_them():
    covered = {type(m) for m in one_of_each()}
    assert covered == set(MESSAGE_TYPES.values()) == set(TOPIC_TYPES.values())
    assert set(TOPIC_TYPES) == {
        "radar/frame",
        "vio/pose",
        "camera/stereo",
        "sar/measurement",
        "twin/template",
        "autofocus/result",
        "image/focused",
        "graph/status",
    }


@pytest.mark.parametrize("msg", one_of_each(), ids=lambda m: type(m).__name__)
def test_bus_and_blob_round_trips_are_bit_exact(msg):
    frames = encode_frames(msg, publisher="tester")
    back, publisher = decode_frames(frames, expect=type(msg))
    assert publisher == "tester"
    assert_same(msg, back)
    assert_same(msg, decode(encode(msg), expect=type(msg)))


@pytest.mark.slow  # 2.9 s (2 cores, idle): out of make test-fast (benchmarks/results/test_fast.json)
def test_large_array_round_trip_and_zero_copy_views():
    big = cplx(780, 86, 256).reshape(-1, 256)  # a whole scan's samples, 137 MB
    m = msgs.SarMeasurement(data=big, positions_m=np.zeros((big.shape[0], 3)), f0_hz=1.0, slope_hz_per_s=1.0, fs_hz=1.0)
    frames = encode_frames(m)
    # The array travels as its own frame, a view of the array's memory (no copy on send).
    data_frame = frames[1]
    assert isinstance(data_frame, memoryview) and data_frame.nbytes == big.nbytes
    assert np.shares_memory(np.frombuffer(data_frame, np.uint8), big)
    # ... and the decoded array is a view of the received frame (no copy on receive).
    received = [bytes(frames[0])] + [bytearray(f) for f in frames[1:]]
    back, _ = decode_frames(received)
    assert np.shares_memory(back.data, np.frombuffer(received[1], np.uint8))
    assert np.array_equal(back.data, big)


def test_non_contiguous_and_castable_inputs_are_normalised():
    data = cplx(10, 8).astype(np.complex128)[:, ::2]  # wrong dtype, non-contiguous
    m = msgs.SarMeasurement(data=data, positions_m=np.zeros((10, 3), np.float32), f0_hz=1, slope_hz_per_s=2, fs_hz=3)
    assert m.data.dtype == np.complex64 and m.positions_m.dtype == np.float64
    back = decode(encode(m))
    assert np.array_equal(back.data, data.astype(np.complex64))


@pytest.mark.parametrize(
    "build, expected",
    [
        (
            lambda: msgs.RadarFrame(
                data=cplx(4, 8), f0_hz=1, slope_hz_per_s=1, fs_hz=1, channel_offsets_m=np.zeros((5, 3))
            ),
            "channel_offsets_m",
        ),
        (
            lambda: msgs.RadarFrame(
                data=np.ones((4, 8)), f0_hz=1, slope_hz_per_s=1, fs_hz=1, channel_offsets_m=np.zeros((4, 3))
            ),
            "ok",
        ),  # real -> complex is a safe cast
        (
            lambda: msgs.RadarFrame(
                data=cplx(4, 8), f0_hz=-1, slope_hz_per_s=1, fs_hz=1, channel_offsets_m=np.zeros((4, 3))
            ),
            "f0_hz",
        ),
        (lambda: msgs.Pose(position_m=np.zeros(3), quat_xyzw=np.array([1.0, 1.0, 0, 0])), "unit quaternion"),
        (lambda: msgs.Pose(position_m=np.zeros(2), quat_xyzw=np.array([0, 0, 0, 1.0])), "position_m"),
        (lambda: msgs.Image(image=np.ones((3, 4), complex), x_m=np.zeros(3), y_m=np.zeros(3)), "x_m"),
        (
            lambda: msgs.StereoFrame(
                left=np.zeros((4, 4), np.uint8), right=np.zeros((4, 5), np.uint8), camera_matrix=np.eye(3)
            ),
            "right",
        ),
        (lambda: msgs.TwinTemplate(image=np.zeros((2, 2), complex), x_m=np.zeros(2), y_m=np.zeros(2), z_m=1), "image"),
        (lambda: msgs.TwinTemplate(**flat_2x2(), phase_rad=np.zeros((2, 3), np.float32)), "phase_rad"),
        (
            lambda: msgs.TwinTemplate(
                image=np.zeros((2, 3), np.float32),
                x_m=np.zeros(3),
                y_m=np.zeros(2),
                z_m=1,
                support=np.ones((3, 2), bool),
            ),
            r"field 'support' must be bool array of shape \(H, W\) or None, got shape \(3, 2\) \(already bound: H=2, W=3\)",
        ),
        (lambda: msgs.TwinTemplate(**flat_2x2(), support=np.ones((2, 2), np.uint8)), "'support' must be bool.*uint8"),
        (lambda: msgs.NodeStatus(received={"a": 1.5}), "received"),
        (lambda: msgs.AutofocusResult(phase_rad=np.zeros(3), loss_history=np.zeros(2), metrics={"a": "x"}), "metrics"),
    ],
)
def test_construction_validates_with_a_message_naming_the_field(build, expected):
    if expected == "ok":
        build()
        return
    with pytest.raises(MessageError, match=expected):
        build()


def _envelope(msg):
    return msgpack.unpackb(encode(msg), raw=False)


def _pack(env):
    return msgpack.packb(env, use_bin_type=True)


def _pose():
    return msgs.Pose(position_m=np.zeros(3), quat_xyzw=np.array([0, 0, 0, 1.0]))


def test_malformed_messages_are_rejected_with_clear_errors():
    pose = _pose()
    with pytest.raises(MessageError, match="not a msgpack message"):
        decode(b"\xc1\xc1garbage")
    with pytest.raises(MessageError, match="not a TwinFocus message envelope"):
        decode(msgpack.packb([1, 2, 3]))
    env = _envelope(pose)
    env["type"] = "Pickle"
    with pytest.raises(MessageError, match="unknown message type 'Pickle'"):
        decode(_pack(env))
    env = _envelope(pose)
    env["v"] = 99
    with pytest.raises(MessageError, match="format version 99"):
        decode(_pack(env))
    env = _envelope(pose)
    env["fields"]["position_m"]["dtype"] = "|O"  # an object array would need pickle: refused
    with pytest.raises(MessageError, match="position_m.*dtype float64"):
        decode(_pack(env))
    env = _envelope(pose)
    env["fields"]["position_m"]["shape"] = [4]
    with pytest.raises(MessageError, match="position_m.*24 bytes.*needs 32"):
        decode(_pack(env))
    env = _envelope(pose)
    env["fields"]["position_m"]["data"] = env["fields"]["position_m"]["data"][:-1]
    with pytest.raises(MessageError, match="position_m"):
        decode(_pack(env))
    env = _envelope(pose)
    env["fields"]["extra"] = 1
    with pytest.raises(MessageError, match="unknown field.*extra"):
        decode(_pack(env))
    env = _envelope(pose)
    del env["fields"]["position_m"]
    with pytest.raises(MessageError, match="'position_m' is missing"):
        decode(_pack(env))
    env = _envelope(pose)
    env["fields"]["header"] = [1, "x", "f"]
    with pytest.raises(MessageError, match="header"):
        decode(_pack(env))
    env = _envelope(pose)
    env["fields"]["confidence"] = "high"
    with pytest.raises(MessageError, match="confidence.*float"):
        decode(_pack(env))
    env = _envelope(pose)
    env["fields"]["quat_xyzw"]["data"] = np.array([1.0, 2, 3, 4]).tobytes()
    with pytest.raises(MessageError, match="unit quaternion"):
        decode(_pack(env))
    with pytest.raises(MessageError, match="expected a RadarFrame message, got Pose"):
        decode(encode(pose), expect=msgs.RadarFrame)
    frames = encode_frames(pose)
    with pytest.raises(MessageError, match="refers to buffer 1, the message has 1"):
        decode_frames(frames[:2])
    assert isinstance(MessageError("x"), TwinFocusError)


def test_optional_arrays_may_be_absent_and_required_ones_may_not():
    frame = one_of_each()[0]
    frame.positions_true_m = None
    back = decode(encode(frame))
    assert back.positions_true_m is None
    env = _envelope(frame)
    env["fields"]["data"] = None
    with pytest.raises(MessageError, match="'data' is missing"):
        decode(_pack(env))


def test_chirp_of_a_frame_is_the_radar_model_chirp():
    f = one_of_each()[0]
    assert f.chirp() == Chirp()


def test_a_result_recorded_before_latency_and_metrics_pending_decodes_with_their_defaults():
    """Logs written before the fields existed: latency 0 (unknown) and a final result."""
    msg = msgs.AutofocusResult(
        header=Header(6, 0, "scene"),
        scan_id="old",
        method="twin",
        phase_rad=np.zeros(3),
        loss_history=np.ones(2),
        latency_s=0.7,
        metrics_pending=True,
    )
    env = msgpack.unpackb(encode(msg), raw=False)
    for name in ("latency_s", "metrics_pending", "estimator"):
        del env["fields"][name]
    old = decode(msgpack.packb(env, use_bin_type=True), msgs.AutofocusResult)
    assert old.latency_s == 0.0 and old.metrics_pending is False and old.scan_id == "old" and old.estimator == ""
    new = decode(encode(msg), msgs.AutofocusResult)
    assert new.latency_s == 0.7 and new.metrics_pending is True


def test_a_template_recorded_before_support_decodes_without_an_outline_and_a_bad_one_is_refused():
    """TwinTemplate.support: absent from logs written before the field (and physical twins'), so
    those decode with None; one that does not fit the image is refused naming the field."""
    msg = one_of_each()[4]
    assert isinstance(msg, msgs.TwinTemplate) and msg.support is not None
    env = _envelope(msg)
    del env["fields"]["support"]
    old = decode(_pack(env), msgs.TwinTemplate)
    assert old.support is None and np.array_equal(old.image, msg.image) and old.source == "stage.npz"
    env = _envelope(msg)
    env["fields"]["support"] = None  # as a physical twin's is sent
    assert decode(_pack(env), msgs.TwinTemplate).support is None
    env = _envelope(msg)
    env["fields"]["support"].update(shape=[40, 30])  # same bytes, transposed shape
    with pytest.raises(
        MessageError,
        match=r"TwinTemplate: field 'support' must be bool array of shape \(H, W\).*"
        r"got shape \(40, 30\) \(already bound: H=30, W=40\)",
    ):
        decode(_pack(env), msgs.TwinTemplate)
    env = _envelope(msg)
    env["fields"]["support"]["dtype"] = "|u1"
    with pytest.raises(MessageError, match="'support' must have dtype bool"):
        decode(_pack(env), msgs.TwinTemplate)
