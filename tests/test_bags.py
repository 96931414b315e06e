"""ROS bag ingestion: round trip synth -> bags -> DemoSet, formats, bad input, recoverable input.

One tiny synthetic data set (one short episode per set, set 2 with LiDAR) is written once per
session in each bag format; bad inputs are made by rewriting the ROS1 bag with rosbags.
"""

from __future__ import annotations

import dataclasses
import json
import warnings
from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag1 import Writer as Writer1
from rosbags.typesys import get_types_from_msg

from diffgcl.cli import bags as bags_cli
from diffgcl.data.bags import BagError, bag_format, inspect_bag, open_bag, typestore_for
from diffgcl.data.demos import DemoSet
from diffgcl.data.ingest import IngestConfig, IngestWarning, ingest_bag, ingest_bags
from diffgcl.data.signals import (
    Signal,
    hold,
    interpolate,
    latlon_to_local,
    local_to_latlon,
    time_grid,
)
from diffgcl.data.synth import SensorModel, SynthConfig, synthesize
from diffgcl.data.topics import TopicMapError, default_topic_map, load_topic_map, parse_topic_map
from diffgcl.sim import hull

NS = 1_000_000_000
TINY = SynthConfig(
    episodes=(1, 1), approach_m=(60.0, 70.0), end_margin_m=(25.0, 30.0), seed=3, max_duration_s=60
)


@pytest.fixture(scope="module")
def synth_sets(tmp_path_factory):
    """{format: SynthResult} of the same tiny data set in the three bag formats."""
    root = tmp_path_factory.mktemp("synth")
    out = {}
    for fmt in ("ros1", "ros2-sqlite3", "ros2-mcap"):
        out[fmt] = synthesize(root / fmt, dataclasses.replace(TINY, fmt=fmt))
    return out


@pytest.fixture(scope="module")
def demos_ros1(synth_sets):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IngestWarning)
        return ingest_bags(list(synth_sets["ros1"].bags))


def _set1_bag(synth_sets) -> Path:
    return [b for b in synth_sets["ros1"].bags if "set1" in b.name][0]


# ---- pieces ----------------------------------------------------------------------------------


def test_default_topic_map_parses():
    tm = default_topic_map()
    assert tm.position.topic == "/odin/nav/odom"
    assert tm.commands.topic == "/odin/operator/cmd"
    assert tm.lidar is not None and tm.lidar.mount == (2.0, 0.0, 0.0)
    assert tm.datum is not None


def test_topic_map_errors(tmp_path):
    with pytest.raises(TopicMapError, match="unknown key"):
        parse_topic_map({"position": "/a", "heading": "/b", "commands": "/c", "speedo": "/d"})
    with pytest.raises(TopicMapError, match="missing required"):
        parse_topic_map({"position": "/a", "heading": "/b"})
    bad = tmp_path / "bad.yaml"
    bad.write_text("position: [unclosed\n")
    with pytest.raises(TopicMapError, match="bad.yaml"):
        load_topic_map(bad)


def test_latlon_local_round_trip():
    datum = (59.413, 10.487)
    xy = np.array([[0.0, 0.0], [120.0, -340.0], [-800.0, 55.5]])
    back = latlon_to_local(*local_to_latlon(xy, datum).T, datum)
    np.testing.assert_allclose(back, xy, atol=1e-6)
    # 1' of latitude is ~1852 m (1855 m at 59.4° on the ellipsoid).
    north = latlon_to_local(np.array([datum[0] + 1 / 60]), np.array([datum[1]]), datum)[0, 1]
    assert 1850 < north < 1860


def test_interpolation_never_crosses_gaps_and_commands_hold():
    t = np.array([0, 1, 2, 5, 6], dtype=np.int64) * NS // 10  # 0, .1, .2, .5, .6 s
    sig = Signal("/x", t, np.arange(5.0)[:, None], max_gap=0.15)
    grid = time_grid(0, 6 * NS // 10, 0.05)
    values, valid = interpolate(sig, grid)
    assert valid.tolist() == [True] * 5 + [False] * 5 + [True] * 3
    np.testing.assert_allclose(values[valid][:5, 0], [0, 0.5, 1, 1.5, 2])
    cmd = Signal("/c", np.array([NS // 10, 4 * NS // 10]), np.array([[1.0], [2.0]]), max_gap=0.0)
    held, ok = hold(cmd, grid)
    assert not ok[:2].any() and ok[2:].all()
    assert held[ok, 0].tolist() == [1.0] * 6 + [2.0] * 5


# ---- round trip ------------------------------------------------------------------------------


def test_round_trip_recovers_states_and_commands(synth_sets, demos_ros1):
    truths = synth_sets["ros1"].episodes
    sm = SensorModel()
    assert demos_ros1.num_episodes == 2
    assert demos_ros1.O.shape[-1] == 53  # the hull env's observation: 32 + 16 beams + 5
    for i, truth in enumerate(truths):
        meta = demos_ros1.episodes[i]
        n = meta["steps"] + 1
        start = int(np.searchsorted(truth.t, meta["t_start_ns"]))
        assert truth.t[start] == meta["t_start_ns"]
        X_true = truth.X[start : start + n]
        U_true = truth.U[start : start + n - 1]
        mask = demos_ros1.mask[i, :n].astype(bool)
        assert mask.mean() > 0.98
        err = (demos_ros1.X[i, :n] - X_true)[mask]
        rms = np.sqrt(np.mean(err**2, axis=0))
        noise = {
            hull.IX_PX: sm.odom_pos,
            hull.IX_PY: sm.odom_pos,
            hull.IX_PSI: sm.imu_yaw,
            hull.IX_VX: sm.odom_vel,
            hull.IX_VY: sm.odom_vel,
            hull.IX_R: sm.imu_rate,
            hull.IX_THRUST: sm.jets_thrust,
            hull.IX_NOZZLE: sm.jets_nozzle,
            hull.IX_OBS_X: sm.obstacle_pos,
            hull.IX_OBS_Y: sm.obstacle_pos,
        }
        # The nozzle follows its command with a 0.24 s lag, sampled at 10 Hz and interpolated
        # linearly: interpolation adds to the sensor noise right after each command change.
        slack = {hull.IX_NOZZLE: 2.0}
        for j, sigma in noise.items():
            k = slack.get(j, 1.0)
            assert rms[j] < 1.5 * k * sigma, (hull.STATE_NAMES[j], rms[j], sigma)
            assert np.quantile(np.abs(err[:, j]), 0.99) < 4 * k * sigma, hull.STATE_NAMES[j]
        # Commands are exact: published on change, held on the grid.
        np.testing.assert_allclose(demos_ros1.U[i, : n - 1], U_true, atol=1e-6)
        assert meta["swerve_side"] == ("left" if truth.profile.side > 0 else "right")
        assert meta["obstacle"] == truth.profile.pole_colour
        assert meta["set"] == str(truth.set)
        assert meta["segmentation"] == "markers"
        assert meta["lidar"] == (truth.set == 2)
    # Set 1 has no LiDAR: a warning recorded in the metadata, not an error.
    assert any("lidar" in w for w in demos_ros1.episodes[0]["warnings"])


def test_lidar_observes_the_pole(demos_ros1):
    """Set 2's LiDAR beams see the pole at about the true distance at some point."""
    i = 1
    layout_beams = 32
    X, O, mask = demos_ros1.X[i], demos_ros1.O[i], demos_ros1.mask[i].astype(bool)
    lidar = O[mask, :layout_beams]
    dist = np.linalg.norm(X[mask][:, hull.SL_OBS] - X[mask][:, :2], axis=1)
    seen = lidar.min(axis=1) < 59.0
    assert seen.sum() > 20
    # Range to the pole surface from the mast (2 m ahead) is within a few metres of the distance.
    assert np.median(np.abs(lidar.min(axis=1)[seen] - dist[seen])) < 3.0


def test_radar_beam_reads_the_pole_with_the_default_filter(synth_sets, demos_ros1):
    """The default map's clutter filter keeps the pole: its radar beam reads it within 5 m in
    most steps; clutter returns (weaker) are gone."""
    from diffgcl.data.scans import radar_pole_beam_hit_rate
    from diffgcl.sim.sensors import SensorLayout

    layout = SensorLayout()
    hits = steps = 0
    for i, truth in enumerate(synth_sets["ros1"].episodes):
        h, n = radar_pole_beam_hit_rate(
            demos_ros1.O[i],
            demos_ros1.X[i],
            demos_ros1.mask[i],
            truth.profile.pole_xy,
            truth.profile.pole_radius,
            layout,
        )
        hits, steps = hits + h, steps + n
    assert steps > 300 and hits / steps >= 0.8, (hits, steps)


def test_ros1_and_ros2_give_the_same_dataset(synth_sets, demos_ros1):
    for fmt in ("ros2-sqlite3", "ros2-mcap"):
        assert bag_format(synth_sets[fmt].bags[0]) == fmt
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", IngestWarning)
            other = ingest_bags(list(synth_sets[fmt].bags))
        for name in ("X", "U", "O", "mask"):
            np.testing.assert_array_equal(getattr(other, name), getattr(demos_ros1, name))
        for a, b in zip(other.episodes, demos_ros1.episodes, strict=True):
            assert {k: v for k, v in a.items() if k not in ("source", "warnings")} == {
                k: v for k, v in b.items() if k not in ("source", "warnings")
            }


def test_navsatfix_position(synth_sets):
    """Positions from the raw GNSS fixes (lat/lon -> local frame) agree within GNSS noise."""
    bag = _set1_bag(synth_sets)
    tm = default_topic_map()
    tm_gps = tm.replace(position=tm.position.__class__("/odin/gps/fix", max_gap=0.5))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IngestWarning)
        (odom,) = ingest_bag(bag, tm)
        (gps,) = ingest_bag(bag, tm_gps)
    m = odom.mask & gps.mask
    err = np.linalg.norm(odom.X[m, :2] - gps.X[m, :2], axis=1)
    assert np.sqrt(np.mean(err**2)) < 2 * SensorModel().gps_pos


def test_segmentation_by_rules_without_markers(synth_sets, tmp_path):
    bag = _set1_bag(synth_sets)
    dst = tmp_path / "nomarkers.bag"
    _rewrite(bag, dst, drop={"/odin/episode"})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IngestWarning)
        (marked,) = ingest_bag(bag)
        (ruled,) = ingest_bag(dst)
    assert ruled.meta["segmentation"] == "rules"
    # The run at the pole: from the approach (no later than the start marker) past the closest
    # approach, ending after the boat is back on its course.
    pole = np.asarray(marked.meta["obstacle_xy"])
    closest = marked.t[np.argmin(np.linalg.norm(marked.X[:, :2] - pole, axis=1))]
    assert ruled.t[0] <= marked.t[0] and ruled.t[-1] > closest + 5 * NS
    assert ruled.meta["swerve_side"] == marked.meta["swerve_side"]


def test_one_bag_per_set(tmp_path):
    cfg = SynthConfig(
        episodes=(2, 0), approach_m=(60.0, 70.0), end_margin_m=(25.0, 30.0), bag_per="set"
    )
    result = synthesize(tmp_path / "perset", cfg)
    assert len(result.bags) == 1
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IngestWarning)
        demos = ingest_bags(list(result.bags))
    assert demos.num_episodes == 2
    assert [m["episode_in_bag"] for m in demos.episodes] == [0, 1]
    manifest = json.loads((tmp_path / "perset" / "manifest.json").read_text())
    assert len(manifest["episodes"]) == 2


# ---- bad input -------------------------------------------------------------------------------


def _rewrite(src: Path, dst: Path, drop=(), edit=None, extra=()):
    """Copy a ROS1 bag; ``edit(topic, t_ns, msg) -> msg`` changes messages; ``extra`` is a list of
    (topic, msgtype, t_ns, msg, typestore) written in addition."""
    store = typestore_for("ros1")
    with open_bag(src) as reader, Writer1(dst) as writer:
        conns = {}
        for c in reader.connections:
            if c.topic in drop:
                continue
            conns[c.topic] = writer.add_connection(
                c.topic, c.msgtype, msgdef=c.msgdef.data, md5sum=c.digest
            )
        rows = []
        for c, t, raw in reader.messages():
            if c.topic in drop:
                continue
            if edit is not None:
                msg = edit(c.topic, t, reader.deserialize(raw, c.msgtype))
                if msg is None:
                    continue
                raw = store.serialize_ros1(msg, c.msgtype)
            rows.append((t, conns[c.topic], raw))
        for topic, msgtype, t, msg, ts in extra:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=ts)
            rows.append((t, conns[topic], ts.serialize_ros1(msg, msgtype)))
        for t, conn, raw in sorted(rows, key=lambda r: r[0]):
            writer.write(conn, t, raw)


def _blob_store():
    store = typestore_for("ros1")
    store.register(get_types_from_msg("uint8[] payload\nstring note\n", "acme_msgs/msg/Blob"))
    return store


def _blobs(topic: str, t0: int, n: int):
    store = _blob_store()
    make = store.types["acme_msgs/msg/Blob"]
    return [
        (
            topic,
            "acme_msgs/msg/Blob",
            t0 + k * NS // 5,
            make(np.arange(4, dtype=np.uint8), "x"),
            store,
        )
        for k in range(n)
    ]


def _stamp_s(msg) -> float:
    return msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9


def _edit_nth(topic: str, n: int, change):
    """An edit for :func:`_rewrite` that applies ``change(msg)`` to the n-th message of topic."""
    seen = {"n": 0}

    def edit(t, when, msg):
        if t == topic:
            seen["n"] += 1
            if seen["n"] == n:
                change(msg)
        return msg

    return edit


def _set_nan(msg):
    msg.pose.pose.position.x = float("nan")


def _three_seconds_back(msg):
    msg.header.stamp.sec -= 3


def _short_episode(topic, t, msg):
    if topic == "/odin/episode" and msg.data == "end":
        return None
    return msg


def _make_bad(kind: str, good: Path, dst: Path) -> tuple[Path, str, str | None]:
    """A bad bag of kind ``kind``; returns (path, expected message part, expected topic)."""
    if kind == "truncated":
        data = good.read_bytes()
        dst.write_bytes(data[: len(data) // 2])
        return dst, "corrupt or truncated", None
    if kind == "corrupt":
        data = bytearray(good.read_bytes())
        mid = len(data) // 2
        data[mid : mid + 64] = b"\xff" * 64
        dst.write_bytes(bytes(data))
        return dst, "corrupt or truncated", None
    if kind == "missing_topic":
        _rewrite(good, dst, drop={"/odin/operator/cmd"})
        return dst, "missing required topic", "/odin/operator/cmd"
    if kind == "unknown_type":
        with open_bag(good) as r:
            t0 = r.start_time
        _rewrite(good, dst, drop={"/odin/imu"}, extra=_blobs("/odin/imu", t0, 200))
        return dst, "unknown message type acme_msgs/msg/Blob", "/odin/imu"
    if kind == "nan":
        _rewrite(good, dst, edit=_edit_nth("/odin/nav/odom", 100, _set_nan))
        return dst, "non-finite", "/odin/nav/odom"
    if kind == "backwards":
        _rewrite(good, dst, edit=_edit_nth("/odin/imu", 300, _three_seconds_back))
        return dst, "time goes backwards", "/odin/imu"
    if kind == "too_short":
        with open_bag(good) as r:
            conn = [c for c in r.connections if c.topic == "/odin/episode"]
            starts = [t for _, t, _ in r.messages(connections=conn)]
        store = typestore_for("ros1")
        end = store.types["std_msgs/msg/String"]("end")
        _rewrite(
            good,
            dst,
            edit=_short_episode,
            extra=[("/odin/episode", "std_msgs/msg/String", starts[0] + 4 * NS, end, store)],
        )
        return dst, "episode too short", "/odin/nav/odom"
    raise ValueError(kind)


BAD = ("truncated", "corrupt", "missing_topic", "unknown_type", "nan", "backwards", "too_short")


@pytest.mark.parametrize("kind", BAD)
def test_bad_input_one_line_error_and_nothing_written(kind, synth_sets, tmp_path, capsys):
    good = _set1_bag(synth_sets)
    bad, expected, topic = _make_bad(kind, good, tmp_path / f"{kind}.bag")
    with pytest.raises(BagError) as info, warnings.catch_warnings():
        warnings.simplefilter("ignore", IngestWarning)
        ingest_bag(bad)
    err = info.value
    assert expected in str(err)
    assert str(bad) in str(err) and "\n" not in str(err)
    if topic is not None:
        assert err.topic == topic
    if kind != "truncated":
        assert err.time_ns is not None and "t=-" not in str(err)
    # Through the CLI: exit status != 0, one line on stderr, no output folder.
    out = tmp_path / f"{kind}_demos"
    code = bags_cli.main(["bags", "convert", str(good), str(bad), "--out", str(out), "--quiet"])
    assert code != 0
    stderr = capsys.readouterr().err.strip().splitlines()
    assert len(stderr) == 1 and stderr[0].startswith("error: ") and str(bad) in stderr[0]
    assert not out.exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(f".{out.name}")]


# ---- recoverable input -----------------------------------------------------------------------


def test_extra_unknown_topic_still_converts(synth_sets, tmp_path, demos_ros1):
    good = _set1_bag(synth_sets)
    with open_bag(good) as r:
        t0 = r.start_time
    dst = tmp_path / "extra.bag"
    _rewrite(good, dst, extra=_blobs("/acme/diagnostics", t0, 50))
    assert "/acme/diagnostics" in {t.topic for t in inspect_bag(dst).topics}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IngestWarning)
        (ep,) = ingest_bag(dst)
    n = ep.X.shape[0]
    np.testing.assert_array_equal(ep.X, demos_ros1.X[0, :n])
    np.testing.assert_array_equal(ep.U, demos_ros1.U[0, : n - 1])


def test_short_dropout_is_masked_with_a_warning(synth_sets, tmp_path):
    good = _set1_bag(synth_sets)
    with open_bag(good) as r:
        t_mid = (r.start_time + r.end_time) // 2

    def drop_odom(topic, t, msg):
        if topic == "/odin/nav/odom" and abs(t - t_mid) < 0.75 * NS:
            return None
        return msg

    dst = tmp_path / "dropout.bag"
    _rewrite(good, dst, edit=drop_odom)
    with pytest.warns(IngestWarning, match="masked"):
        (ep,) = ingest_bag(dst)
    gap = np.abs(ep.t - t_mid) < 0.5 * NS
    assert not ep.mask[gap].any()
    assert ep.mask.mean() > 0.9
    assert np.isfinite(ep.X).all()


def test_cli_synth_inspect_convert(tmp_path, capsys):
    out = tmp_path / "cli"
    argv = ["bags", "synth", "--out", str(out), "--episodes-per-set", "1", "0", "--short"]
    assert bags_cli.main([*argv, "--quiet", "--format", "ros2-mcap"]) == 0
    assert bags_cli.main(["bags", "inspect", str(out)]) == 0
    text = capsys.readouterr().out
    assert "/odin/operator/cmd" in text and "odin_msgs/msg/JetCommand" in text
    demos_dir = tmp_path / "demos"
    assert bags_cli.main(["bags", "convert", str(out), "--out", str(demos_dir), "--quiet"]) == 0
    demos = DemoSet.load(demos_dir)
    assert demos.num_episodes == 1 and demos.env == "hull"
    assert IngestConfig().dt == pytest.approx(demos.dt)


def test_pointcloud2_points_in_hull_frame():
    """A PointCloud2 (x, y, z float32, 16-byte points) becomes hull-frame points (mount applied)."""
    from diffgcl.data.bags import TopicMessages
    from diffgcl.data.scans import decode_scans
    from diffgcl.data.topics import RangeSensorSpec

    store = typestore_for("ros2-mcap")
    pts = np.array([[10.0, 0.0, 1.0, 0.0], [0.0, -5.0, 0.5, 0.0], [np.nan, 1.0, 0.0, 0.0]])
    field = store.types["sensor_msgs/msg/PointField"]
    fields = [field(n, 4 * k, 7, 1) for k, n in enumerate("xyz")]
    time = store.types["builtin_interfaces/msg/Time"](1, 0)
    header = store.types["std_msgs/msg/Header"](time, "lidar")
    raw = pts.astype("<f4").tobytes()
    cloud = store.types["sensor_msgs/msg/PointCloud2"](
        header, 1, 3, fields, False, 16, 48, np.frombuffer(raw, np.uint8), True
    )
    data = TopicMessages(
        "/cloud", "sensor_msgs/msg/PointCloud2", np.array([NS]), np.array([NS]), (cloud,)
    )
    spec = RangeSensorSpec("/cloud", mount=(2.0, 0.0, np.pi / 2))
    (xy,) = decode_scans("test.bag", data, spec, "lidar").points
    # Sensor yawed 90° to port, 2 m ahead: (10, 0) -> (2, 10); (0, -5) -> (7, 0); NaN dropped.
    np.testing.assert_allclose(xy, [[2.0, 10.0], [7.0, 0.0]], atol=1e-6)


def test_lidar_beams_match_the_simulated_sensor(synth_sets, demos_ros1):
    """Ingested LiDAR beams agree with the env's mjx.ray beams at the ingested states."""
    import jax

    from diffgcl.envs.hull import make_hull_env

    i = 1
    truth = synth_sets["ros1"].episodes[i]
    assert truth.set == 2
    mask = demos_ros1.mask[i].astype(bool)
    X = demos_ros1.X[i][mask]
    env = make_hull_env(poles=[X[0, hull.SL_OBS]], pole_radius=truth.profile.pole_radius)
    sim = np.asarray(jax.jit(jax.vmap(env.ranges))(jax.numpy.asarray(X)))
    n = env.layout.lidar_beams
    bag, sim = demos_ros1.O[i][mask, :n], sim[:, :n]
    sim_hit = sim < env.layout.lidar_range - 1e-6
    bag_hit = bag < env.layout.lidar_range - 1e-6
    both = sim_hit & bag_hit
    assert sim_hit.sum() > 10
    assert both.sum() >= 0.75 * sim_hit.sum()
    # Each return is a disc of layout.point_radius (0.25 m): readings agree to about that.
    assert np.median(np.abs(sim[both] - bag[both])) < 0.5
