"""BagPlayer: delivery, ordering, recorded QoS, rate, remapping (rclpy in-process, isolated context)."""

from __future__ import annotations

import threading
import time
from collections import defaultdict

import numpy as np
import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from gpis_grasp_ros.data import bagio
from gpis_grasp_ros.data import messages as cv
from gpis_grasp_ros.data.topics import GROUND_TRUTH_TOPICS
from gpis_grasp_ros.ros import conversions as rcv
from gpis_grasp_ros.ros import player
from gpis_grasp_ros.sim.scene import MaterialRegion, SceneSpec, write_scene_bag

SQUARE = np.array([[-0.03, -0.02], [0.04, -0.02], [0.04, 0.02], [-0.03, 0.02]])


@pytest.fixture(scope='module')
def bag(tmp_path_factory):
    spec = SceneSpec(outline=SQUARE, regions=[MaterialRegion.box('transparent', 0.02, -0.03, 0.05, 0.03)],
                     height=0.02, frames=4, seed=3)
    return write_scene_bag(spec, tmp_path_factory.mktemp('player') / 'p.mcap')


@pytest.fixture(scope='module')
def context():
    ctx = Context()
    rclpy.init(context=ctx)
    yield ctx
    rclpy.try_shutdown(context=ctx)


@pytest.fixture
def executor(context):
    """An executor spinning in a background thread; nodes added to it are destroyed afterwards."""
    ex = SingleThreadedExecutor(context=context)
    thread = threading.Thread(target=ex.spin, daemon=True)
    thread.start()
    yield ex
    for node in list(ex.get_nodes()):
        ex.remove_node(node)
        node.destroy_node()
    ex.shutdown(timeout_sec=2.0)
    thread.join(timeout=2.0)


class Recorder:
    """A node subscribed to topics, recording (topic, header stamp) in arrival order."""

    def __init__(self, context, executor, topics: dict[str, str], qos: QoSProfile, name: str = 'recorder'):
        self.node = rclpy.create_node(name, context=context)
        self.received: list[tuple[str, int]] = []
        self.messages: dict[str, list] = defaultdict(list)
        self.lock = threading.Lock()
        for topic, msgtype in topics.items():
            self.node.create_subscription(rcv.rclpy_message_class(msgtype), topic,
                                          lambda msg, t=topic: self._on(t, msg), qos)
        executor.add_node(self.node)

    def _on(self, topic, msg):
        with self.lock:
            self.received.append((topic, cv.stamp_to_ns(msg.header)))
            self.messages[topic].append(msg)

    def wait_for(self, count: int, timeout: float = 10.0) -> int:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self.lock:
                if len(self.received) >= count:
                    break
            time.sleep(0.01)
        time.sleep(0.05)  # let anything extra arrive
        with self.lock:
            return len(self.received)


RELIABLE_DEEP = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE,
                           durability=DurabilityPolicy.VOLATILE)


def test_qos_from_recorded_profiles():
    latched = player.qos_from_recorded([bagio.LATCHED_QOS])
    assert (latched.reliability, latched.durability, latched.depth) == \
        (ReliabilityPolicy.RELIABLE, DurabilityPolicy.TRANSIENT_LOCAL, 1)
    sensor = player.qos_from_recorded([bagio.SENSOR_QOS])
    assert (sensor.reliability, sensor.durability, sensor.depth) == \
        (ReliabilityPolicy.BEST_EFFORT, DurabilityPolicy.VOLATILE, 5)
    mixed = player.qos_from_recorded([bagio.LATCHED_QOS, bagio.SENSOR_QOS])
    assert (mixed.reliability, mixed.durability, mixed.depth) == \
        (ReliabilityPolicy.BEST_EFFORT, DurabilityPolicy.VOLATILE, 5)
    assert player.qos_from_recorded([]).reliability == ReliabilityPolicy.RELIABLE


def test_every_message_delivered_in_order(context, executor, bag):
    info = bagio.bag_topics(bag)
    expected = [(r.topic, cv.stamp_to_ns(m.header))
                for r, (_, _, _, m) in zip(bagio.iter_bag(bag), bagio.read_messages(bag), strict=True)]
    rec = Recorder(context, executor, {t: v['type'] for t, v in info.items()}, RELIABLE_DEEP)
    bp = player.BagPlayer(context, bag, rate=0.0, reliable=True, wait_for_subscribers=5.0)
    try:
        t0 = time.monotonic()
        bp.play_once(blocking=True)
        assert bp.done.is_set() and bp.error is None
        assert rec.wait_for(len(expected)) == len(expected)
        assert time.monotonic() - t0 < 10.0
    finally:
        bp.destroy()
    assert sum(bp.counts.values()) == len(expected) == 4 + 5 * 4
    assert sorted(rec.received) == sorted(expected)
    for topic in info:  # per-topic order is the bag's order
        assert [s for t, s in rec.received if t == topic] == [s for t, s in expected if t == topic]
    # the published bytes are real messages: the cloud converts to the recorded data
    cloud = rec.messages['/camera/depth/points'][0]
    recorded = next(m for t, _, _, m in bagio.read_messages(bag, ['/camera/depth/points']))
    np.testing.assert_array_equal(cv.pointcloud2_to_xyz_rgb(cloud)[0], cv.pointcloud2_to_xyz_rgb(recorded)[0])


def test_recorded_qos_latched_ground_truth(context, executor, bag):
    """Ground truth is latched: a TRANSIENT_LOCAL subscriber created after playback still gets it."""
    types = {t: v['type'] for t, v in bagio.bag_topics(bag).items()}
    bp = player.BagPlayer(context, bag, rate=0.0, topics=GROUND_TRUTH_TOPICS, wait_for_subscribers=0.0)
    try:
        assert bp.qos['/ground_truth/sdf'].durability == DurabilityPolicy.TRANSIENT_LOCAL
        bp.play_once(blocking=True)
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        late = Recorder(context, executor, {t: types[t] for t in GROUND_TRUTH_TOPICS}, latched, name='late')
        assert late.wait_for(len(GROUND_TRUTH_TOPICS)) == len(GROUND_TRUTH_TOPICS)
        occ, geom = cv.occupancy_grid_to_numpy(late.messages['/ground_truth/occupancy'][0])
        assert (occ == 100).sum() * geom.resolution ** 2 == pytest.approx(0.07 * 0.04, rel=0.02)
        volatile = Recorder(context, executor, {'/ground_truth/sdf': types['/ground_truth/sdf']},
                            RELIABLE_DEEP, name='volatile')
        assert volatile.wait_for(1, timeout=0.5) == 0  # a volatile subscriber does not get the stored sample
    finally:
        bp.destroy()


def test_sensor_topics_are_best_effort(context, bag):
    bp = player.BagPlayer(context, bag, topics=['camera/depth/points'])
    try:
        assert list(bp.publishers) == ['/camera/depth/points']
        assert bp.qos['/camera/depth/points'].reliability == ReliabilityPolicy.BEST_EFFORT
    finally:
        bp.destroy()


def test_real_time_rate_and_remap(context, executor, bag):
    rec = Recorder(context, executor, {'/sim/rgb': 'sensor_msgs/msg/Image'}, RELIABLE_DEEP, name='remapped')
    bp = player.BagPlayer(context, bag, rate=0.5, topics=['/camera/rgb/image_raw'],
                          remap={'camera/rgb/image_raw': '/sim/rgb'}, reliable=True, wait_for_subscribers=5.0)
    try:
        t0 = time.monotonic()
        bp.play_once(blocking=False)
        assert bp.done.wait(5.0)
        elapsed = time.monotonic() - t0
    finally:
        bp.destroy()
    # 4 frames 1/30 s apart at half speed: 3 intervals of 1/15 s
    assert elapsed >= 0.9 * 3 / 15
    assert rec.wait_for(4) == 4


def test_loop_and_stop(context, bag):
    bp = player.BagPlayer(context, bag, rate=0.0, loop=True, topics=['/camera/rgb/camera_info'],
                          wait_for_subscribers=0.0)
    try:
        bp.play(blocking=False)
        deadline = time.monotonic() + 5.0
        while bp.passes < 3 and time.monotonic() < deadline:
            time.sleep(0.01)
        bp.stop()
        assert bp.done.is_set() and bp.passes >= 3 and bp.error is None
        assert bp.counts['/camera/rgb/camera_info'] >= 12
    finally:
        bp.destroy()


def test_bad_arguments(context, bag, tmp_path):
    with pytest.raises(FileNotFoundError):
        player.BagPlayer(context, tmp_path / 'missing.mcap')
    with pytest.raises(ValueError, match='not in'):
        player.BagPlayer(context, bag, topics=['/nope'])
    with pytest.raises(ValueError, match='cannot remap'):
        player.BagPlayer(context, bag, remap={'/nope': '/x'})
    with pytest.raises(ValueError, match='rate'):
        player.BagPlayer(context, bag, rate=-1)
    assert player.main([str(tmp_path / 'missing.mcap')]) == 2
    assert player.main([str(bag), '--remap', 'nonsense']) == 2


def test_main_plays_a_bag(bag, capsys):
    """The command line runs in the default context and shuts it down again."""
    assert player.main([str(bag), '--rate', '0', '--wait-for-subscribers', '0', '--topics',
                        '/camera/rgb/camera_info']) == 0
    assert not rclpy.ok()


def test_reliable_replay_keeps_every_frame_until_acknowledged(context):
    """The shipped bags record depth 5 for 10 frames: a reliable KEEP_LAST 5 writer may drop its oldest
    unacknowledged frame, so ``reliable=True`` deepens the history to the topic's message count."""
    from pathlib import Path
    shipped = Path(__file__).resolve().parents[2] / 'bags' / 'A_tape_dispenser.mcap'
    info = bagio.bag_topics(shipped)
    assert info['/camera/depth/points']['count'] == 10
    assert all(q.depth == 5 for q in info['/camera/depth/points']['qos'])
    for reliable, depth, policy in ((True, 10, ReliabilityPolicy.RELIABLE), (False, 5, ReliabilityPolicy.BEST_EFFORT)):
        bp = player.BagPlayer(context, shipped, rate=0.0, reliable=reliable, wait_for_subscribers=0.0)
        try:
            for topic in ('/camera/depth/points', '/camera/rgb/image_raw'):
                assert (bp.qos[topic].depth, bp.qos[topic].reliability) == (depth, policy)
                assert bp.qos[topic].history == HistoryPolicy.KEEP_LAST
            assert bp.qos['/ground_truth/sdf'].depth == 1  # one message: nothing to deepen
        finally:
            bp.destroy()


def test_required_topic_holds_playback_until_matched(context, executor, bag):
    """``require``: playback waits for a subscriber on the topic even when other topics are matched."""
    with pytest.raises(ValueError, match='not in the bag'):
        player.BagPlayer(context, bag, require=['/no/such/topic'])
    types = {t: v['type'] for t, v in bagio.bag_topics(bag).items()}
    remap = {'/camera/depth/points': '/req_test/points', '/ground_truth/sdf': '/req_test/sdf'}
    other = Recorder(context, executor, {'/req_test/sdf': types['/ground_truth/sdf']}, RELIABLE_DEEP, name='gt')
    bp = player.BagPlayer(context, bag, rate=0.0, reliable=True, wait_for_subscribers=30.0, remap=remap,
                          topics=list(remap), require=['camera/depth/points'])
    try:
        assert bp.require == ['/camera/depth/points']
        bp.play_once(blocking=False)
        time.sleep(2.0)  # longer than the graph settle that would otherwise start playback
        assert not bp.done.is_set() and sum(bp.counts.values()) == 0 and other.wait_for(1, timeout=0.0) == 0
        late = Recorder(context, executor, {'/req_test/points': types['/camera/depth/points']}, RELIABLE_DEEP,
                        name='late_cloud')
        assert late.wait_for(4) == 4  # every frame reaches the subscriber that arrived late
        assert other.wait_for(1) == 1
        assert bp.join(10.0) and bp.error is None
    finally:
        bp.destroy()
