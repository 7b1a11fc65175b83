"""Bag replay with rclpy publishers: a launch-free stand-in for ``ros2 bag play``.

``gpis-grasp play BAG [--rate R] [--loop] [--topics T ...] [--remap FROM:=TO ...] [--reliable] [--clock]``
(also installed as the ``bag_player`` console script).

* **No lost frames to discovery.** Before the first message the player waits (up to
  ``wait_for_subscribers``, default 5 s) until every topic that has subscribers in the ROS graph is
  matched by its publisher and the graph has been stable for a moment: a player started after
  the nodes would otherwise publish a short bag before DDS discovery connected them. At the end
  it waits until reliable subscribers acknowledged everything, and reports per-topic counts.
* ``--clock`` publishes ``/clock`` (rosgraph_msgs/Clock) with the bag time of each message before
  it, like ``ros2 bag play --clock`` (run the nodes with ``use_sim_time:=true`` to use it).

* Messages are published in bag-time order as the recorded CDR bytes (no re-serialization),
  each topic with the QoS it was recorded with (``offered_qos_profiles``; several offered
  profiles are merged like rosbag2 does: RELIABLE / TRANSIENT_LOCAL only if all agree), so the
  latched ground truth reaches late TRANSIENT_LOCAL subscribers and camera streams are best effort.
* ``rate`` scales real time (1.0 = recorded timing); ``rate=0`` publishes as fast as the
  subscribers allow: before the first message it waits (up to ``wait_for_subscribers`` s) until
  every publisher is matched, and after each message on a RELIABLE publisher it waits until all
  matched subscribers acknowledged it. Best-effort topics cannot be paced that way; use
  ``reliable=True`` (``--reliable``) to publish every topic RELIABLE (still compatible with
  best-effort subscribers) when no message may be lost. A reliable KEEP_LAST writer drops its
  oldest not-yet-acknowledged message once ``depth`` newer ones are queued (the shipped bags record
  depth 5 for 10 camera frames sent in 0.33 s: one slow repair of a lost fragment lost frames), so
  ``reliable=True`` also raises each topic's history depth to its message count in the bag
  (at most :data:`MAX_RELIABLE_DEPTH`). A best-effort subscriber never acknowledges, so a
  reliable topic one subscribes to cannot be paced by acknowledgements (each message would wait
  ``ack_timeout``): with ``rate=0`` the player says so before the first message and publishes that
  topic at its recorded timing instead (bursts stay bursts; the other topics go as fast as acknowledged).
* Header stamps are left as recorded (2015 for the shipped bags).

:class:`BagPlayer` is importable for tests and demos: give it a node (it adds publishers) or a
context (it creates its own ``bag_player`` node), call :meth:`BagPlayer.play_once` or
:meth:`BagPlayer.play`, and wait on :attr:`BagPlayer.done`.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import rclpy
from rclpy.context import Context
from rclpy.duration import Duration
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, LivelinessPolicy, QoSProfile, ReliabilityPolicy
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability
from rosgraph_msgs.msg import Clock

from gpis_grasp_ros.data import bagio
from gpis_grasp_ros.ros.conversions import rclpy_message_class

_INFINITE_SEC = 2 ** 31 - 1  # rosbag2 stores "infinite" as 9223372036 s; anything this large is "default"
#: Largest writer history depth ``reliable=True`` asks for (messages of one topic kept until acknowledged).
MAX_RELIABLE_DEPTH = 1000

#: Default bound (s) of the wait for subscribers before the first message.
DEFAULT_WAIT = 5.0
#: The matched/graph state (nodes seen, subscribers per topic) must be unchanged this long (s)
#: before playback starts: endpoints of different nodes are discovered at different times, and a
#: shorter settle (0.3 s) lost whole replays to a late-discovered segmentation_node on a loaded machine.
GRAPH_SETTLE = 1.0
CLOCK_QOS = QoSProfile(depth=10, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.VOLATILE)


def _duration(t: Any) -> Duration | None:
    sec, nsec = int(t.sec), int(t.nsec)
    if (sec == 0 and nsec == 0) or sec >= _INFINITE_SEC:
        return None
    return Duration(seconds=sec, nanoseconds=nsec)


def qos_from_recorded(profiles: Iterable[Qos], depth_default: int = 10) -> QoSProfile:
    """rclpy :class:`QoSProfile` for publishing a topic recorded with ``profiles`` (rosbags Qos).

    Several profiles (several recorded publishers) are merged like rosbag2 play does: RELIABLE and
    TRANSIENT_LOCAL only when every profile has them; the largest depth. No profile → a
    RELIABLE / VOLATILE KEEP_LAST ``depth_default`` profile."""
    profiles = list(profiles)
    if not profiles:
        return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth_default,
                          reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
    reliable = all(p.reliability == QosReliability.RELIABLE for p in profiles)
    latched = all(p.durability == QosDurability.TRANSIENT_LOCAL for p in profiles)
    keep_all = any(p.history == QosHistory.KEEP_ALL for p in profiles)
    kwargs: dict[str, Any] = {
        'history': HistoryPolicy.KEEP_ALL if keep_all else HistoryPolicy.KEEP_LAST,
        'depth': max(max(int(p.depth) for p in profiles), 1),
        'reliability': ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        'durability': DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE,
    }
    first = profiles[0]
    if len(profiles) == 1:
        for name in ('deadline', 'lifespan', 'liveliness_lease_duration'):
            d = _duration(getattr(first, name))
            if d is not None:
                kwargs[name] = d
        if first.liveliness == QosLiveliness.MANUAL_BY_TOPIC:
            kwargs['liveliness'] = LivelinessPolicy.MANUAL_BY_TOPIC
    return QoSProfile(**kwargs)


def _absolute(topic: str) -> str:
    return topic if topic.startswith('/') else '/' + topic


class BagPlayer:
    """Publish the messages of one bag with rclpy (see the module docstring).

    Args:
        node_or_context: an rclpy ``Node`` to create the publishers on, or a ``Context`` (or None
            for the default context) in which a ``bag_player`` node is created and owned.
        bag_path: ``.mcap`` file or rosbag2 directory.
        rate: playback speed factor; 0 = as fast as the subscribers allow.
        loop: :meth:`play` repeats until :meth:`stop`.
        topics: topics to play (default all; with or without the leading '/').
        remap: recorded topic → published topic.
        reliable: publish every topic RELIABLE (otherwise the recorded reliability), with a history
            depth of at least the topic's message count (up to :data:`MAX_RELIABLE_DEPTH`).
        wait_for_subscribers: seconds to wait at most before the first message until every topic
            with subscribers in the graph is matched (default :data:`DEFAULT_WAIT`; 0 = do not wait).
        clock: publish ``/clock`` with the bag time of each message.
        require: recorded topics that must have a matched subscriber before playback starts (bounded
            by ``wait_for_subscribers``). A process that joins a running graph discovers the other
            processes one by one, some only at a later discovery announcement (seconds apart), so
            "the graph has been stable for a moment" alone can start playback before a slow-to-discover
            node's subscription is known; with a required topic that replay is not lost.
        ack_timeout: seconds to wait for acknowledgements of each message when ``rate == 0``.
    """

    def __init__(self, node_or_context: Node | Context | None, bag_path: str | Path, rate: float = 1.0,
                 loop: bool = False, topics: Iterable[str] | None = None, remap: Mapping[str, str] | None = None,
                 *, reliable: bool = False, wait_for_subscribers: float | None = None,
                 ack_timeout: float = 5.0, clock: bool = False, require: Iterable[str] = ()) -> None:
        if not (rate >= 0):
            raise ValueError(f'rate must be >= 0 (0 = as fast as possible), got {rate}')
        self.bag_path = Path(bag_path)
        if not self.bag_path.exists():
            raise FileNotFoundError(f'bag {self.bag_path} does not exist')
        self.rate = float(rate)
        self.loop = bool(loop)
        self.ack_timeout = float(ack_timeout)
        self.wait_for_subscribers = DEFAULT_WAIT if wait_for_subscribers is None else float(wait_for_subscribers)
        info = bagio.bag_topics(self.bag_path)
        self.require = sorted({_absolute(t) for t in require})
        unknown = [t for t in self.require if t not in info]
        if unknown:
            raise ValueError(f"required topic(s) {', '.join(unknown)} not in the bag")
        if topics is None:
            selected = sorted(info)
        else:
            selected = sorted({_absolute(t) for t in topics})
            missing = [t for t in selected if t not in info]
            if missing:
                raise ValueError(f"topic(s) {', '.join(missing)} not in {self.bag_path}; "
                                 f"it has {', '.join(sorted(info))}")
        remap = {_absolute(k): _absolute(v) for k, v in (remap or {}).items()}
        unknown = [k for k in remap if k not in info]
        if unknown:
            raise ValueError(f"cannot remap {', '.join(unknown)}: not in {self.bag_path}")

        self._owns_node = not isinstance(node_or_context, Node)
        if isinstance(node_or_context, Node):
            self.node = node_or_context
        else:
            self.node = rclpy.create_node('bag_player', context=node_or_context)
        self.topics = selected
        self.remap = remap
        self.publishers: dict[str, Any] = {}
        self.clock_pub = None
        self.qos: dict[str, QoSProfile] = {}
        try:
            for topic in selected:
                qos = qos_from_recorded(info[topic]['qos'])
                if reliable:
                    qos.reliability = ReliabilityPolicy.RELIABLE
                    count = int(info[topic].get('count', 0) or 0)
                    if qos.history == HistoryPolicy.KEEP_LAST:
                        qos.depth = max(qos.depth, min(count, MAX_RELIABLE_DEPTH))
                msg_class = rclpy_message_class(info[topic]['type'])
                self.qos[topic] = qos
                self.publishers[topic] = self.node.create_publisher(msg_class, remap.get(topic, topic), qos)
            self.clock_pub = self.node.create_publisher(Clock, '/clock', CLOCK_QOS) if clock else None
        except BaseException:
            for pub in self.publishers.values():
                self.node.destroy_publisher(pub)
            if self._owns_node:
                self.node.destroy_node()
            raise
        self.counts: dict[str, int] = dict.fromkeys(selected, 0)
        self.passes = 0
        self.done = threading.Event()
        self.error: BaseException | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        #: reliable topics with a best-effort subscriber: paced by the recorded timing when rate == 0
        self.time_paced: set[str] = set()

    # ------------------------------------------------------------------ control
    def play_once(self, blocking: bool = True) -> None:
        """Play the bag once (ignores ``loop``); in a background thread when ``blocking`` is False."""
        self._start(once=True, blocking=blocking)

    def play(self, blocking: bool = True) -> None:
        """Play the bag, repeating while ``loop`` is set and :meth:`stop` was not called."""
        self._start(once=not self.loop, blocking=blocking)

    def stop(self, timeout: float | None = 5.0) -> None:
        """Stop playback (between messages) and wait up to ``timeout`` s for the thread."""
        self._stop.set()
        self.join(timeout)

    def join(self, timeout: float | None = None) -> bool:
        """Wait for background playback; returns True when it has finished."""
        if self._thread is not None:
            self._thread.join(timeout)
        return self.done.is_set()

    def destroy(self) -> None:
        """Stop, destroy the publishers, and the node if the player created it."""
        self.stop()
        for pub in self.publishers.values():
            self.node.destroy_publisher(pub)
        self.publishers.clear()
        if self.clock_pub is not None:
            self.node.destroy_publisher(self.clock_pub)
            self.clock_pub = None
        if self._owns_node:
            self.node.destroy_node()

    # ------------------------------------------------------------------ playback
    def _start(self, once: bool, blocking: bool) -> None:
        if self._thread is not None and self._thread.is_alive():
            raise RuntimeError('playback is already running')
        self.done.clear()
        self._stop.clear()
        self.error = None
        if blocking:
            self._run(once)
            if self.error is not None:
                raise self.error
        else:
            self._thread = threading.Thread(target=self._run, args=(once,), name='bag_player', daemon=True)
            self._thread.start()

    def best_effort_subscribers(self) -> dict[str, list[str]]:
        """Reliable-published topics → the nodes subscribing to them best effort (they never acknowledge)."""
        out: dict[str, list[str]] = {}
        for topic, pub in self.publishers.items():
            if self.qos[topic].reliability != ReliabilityPolicy.RELIABLE:
                continue
            names = [f'{i.node_namespace.rstrip("/")}/{i.node_name}'
                     for i in self.node.get_subscriptions_info_by_topic(pub.topic_name)
                     if i.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT]
            if names:
                out[topic] = names
        return out

    def _choose_pacing(self) -> None:
        """With rate 0: topics that acknowledgements cannot pace go at their recorded timing (said once)."""
        self.time_paced = set()
        if self.rate != 0:
            return
        best_effort = self.best_effort_subscribers()
        for topic, names in best_effort.items():
            self.node.get_logger().warning(
                f"{topic}: subscribed best effort by {', '.join(names)}; a best-effort subscriber never "
                'acknowledges, so this topic cannot be played as fast as acknowledged: it is played at its '
                'recorded timing (run the subscriber with reliable input, e.g. input_reliability:=reliable, '
                'for full speed)')
        self.time_paced = set(best_effort)

    def _run(self, once: bool) -> None:
        try:
            self._wait_for_matching()
            self._choose_pacing()
            while not self._stop.is_set():
                self._play_pass()
                self.passes += 1
                if once:
                    break
        except BaseException as err:  # noqa: BLE001 - reported through self.error / done
            if self.node.context.ok() and not self._stop.is_set():
                self.error = err
                self.node.get_logger().error(f'playback of {self.bag_path} failed: {err}')
        finally:
            self.done.set()

    def unmatched(self) -> tuple[dict[str, int], bool]:
        """Graph subscribers not yet matched per topic ({topic: missing}) and whether any topic is matched."""
        missing, any_matched = {}, False
        for topic, pub in self.publishers.items():
            matched = pub.get_subscription_count()
            in_graph = self.node.count_subscribers(pub.topic_name)
            any_matched = any_matched or matched > 0
            if in_graph > matched or in_graph == 0:
                missing[topic] = max(in_graph - matched, 0)
        return missing, any_matched

    def _wait_for_matching(self) -> None:
        """Wait until every topic with subscribers in the graph is matched and the graph is stable.

        Topics nobody subscribes to do not hold playback up once another topic is matched; with no
        subscriber at all the player waits the whole ``wait_for_subscribers`` and plays anyway.
        """
        if self.wait_for_subscribers <= 0:
            return
        deadline = time.monotonic() + self.wait_for_subscribers
        last_state, stable_since = None, time.monotonic()
        while not self._stop.is_set():
            missing, any_matched = self.unmatched()
            state = (tuple(sorted(missing.items())), any_matched, len(self.node.get_node_names_and_namespaces()))
            now = time.monotonic()
            if state != last_state:
                last_state, stable_since = state, now
            unmatched_with_subs = any(n > 0 for n in missing.values())
            unmet = [t for t in self.require
                     if t in self.publishers and self.publishers[t].get_subscription_count() == 0]
            if any_matched and not unmatched_with_subs and not unmet and now - stable_since >= GRAPH_SETTLE:
                return
            if now >= deadline:
                lonely = [t for t, n in missing.items() if n == 0]
                late = [t for t, n in missing.items() if n > 0]
                text = []
                if late:
                    text.append(f"subscribers not yet matched on {', '.join(late)}")
                if lonely and not any_matched:
                    text.append('no subscriber on any topic')
                if unmet:
                    text.append(f"no subscriber on required {', '.join(unmet)}")
                if text:
                    self.node.get_logger().warning('; '.join(text) + f' after {self.wait_for_subscribers:g} s; '
                                                   'playing anyway')
                return
            self._stop.wait(0.02)

    def _wait_for_acks(self) -> None:
        """Wait (bounded) until reliable subscribers acknowledged everything published."""
        ack = Duration(seconds=self.ack_timeout)
        for topic, pub in self.publishers.items():
            if self.qos[topic].reliability == ReliabilityPolicy.RELIABLE and pub.get_subscription_count() > 0:
                if not pub.wait_for_all_acked(ack):
                    self.node.get_logger().warning(f'{topic}: not acknowledged within {self.ack_timeout} s')

    def _play_pass(self) -> None:
        start_wall: float | None = None
        start_bag = 0
        ack = Duration(seconds=self.ack_timeout)
        last_t_ns: int | None = None
        for record in bagio.iter_bag(self.bag_path, self.topics):
            if self._stop.is_set():
                return
            if start_wall is None:
                start_wall, start_bag = time.monotonic(), record.t_ns
            if self.rate > 0:
                due = start_wall + (record.t_ns - start_bag) * 1e-9 / self.rate
                delay = due - time.monotonic()
                if delay > 0 and self._stop.wait(delay):
                    return
            elif record.topic in self.time_paced and last_t_ns is not None:
                gap = min(max((record.t_ns - last_t_ns) * 1e-9, 0.0), 1.0)  # the recorded gap, at most 1 s
                if gap > 0 and self._stop.wait(gap):
                    return
            last_t_ns = record.t_ns
            pub = self.publishers[record.topic]
            if self.clock_pub is not None:
                sec, nsec = divmod(int(record.t_ns), 1_000_000_000)
                clock_msg = Clock()
                clock_msg.clock.sec, clock_msg.clock.nanosec = sec, nsec
                self.clock_pub.publish(clock_msg)
            pub.publish(record.raw)
            self.counts[record.topic] += 1
            if (self.rate == 0 and self.qos[record.topic].reliability == ReliabilityPolicy.RELIABLE
                    and record.topic not in self.time_paced):
                if not pub.wait_for_all_acked(ack):
                    self.node.get_logger().warning(f'{record.topic}: not acknowledged within {self.ack_timeout} s')
        if self.rate > 0 and not self._stop.is_set():
            self._wait_for_acks()


# =========================================================================== command line
def _parse_remap(items: Iterable[str]) -> dict[str, str]:
    out: dict[str, str] = {}
    for item in items:
        src, sep, dst = item.partition(':=')
        if not sep or not src or not dst:
            raise ValueError(f"--remap '{item}': expected FROM:=TO")
        out[src] = dst
    return out


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog='gpis-grasp play', description='Replay a bag with rclpy publishers '
                                '(recorded QoS; a ros2 bag play stand-in).')
    p.add_argument('bag', help='.mcap file or rosbag2 directory')
    p.add_argument('--rate', type=float, default=1.0, help='speed factor, 0 = as fast as subscribers allow')
    p.add_argument('--loop', action='store_true', help='repeat until interrupted')
    p.add_argument('--topics', nargs='+', default=None, help='only these topics')
    p.add_argument('--remap', nargs='+', default=[], metavar='FROM:=TO', help='rename topics')
    p.add_argument('--reliable', action='store_true', help='publish every topic RELIABLE')
    p.add_argument('--wait-for-subscribers', type=float, default=None, metavar='SEC',
                   help=f'wait up to SEC until every topic with subscribers in the graph is matched '
                        f'(default {DEFAULT_WAIT:g}; 0 = do not wait)')
    p.add_argument('--require', nargs='+', default=[], metavar='TOPIC',
                   help='recorded topics that must have a matched subscriber before the first message '
                        '(waited for up to --wait-for-subscribers s)')
    p.add_argument('--clock', action='store_true', help='publish /clock with the bag time of each message')
    p.add_argument('--keep-alive', action='store_true',
                   help='keep the (latched) publishers alive after playback until interrupted')
    return p


def main(argv: list[str] | None = None) -> int:
    """``gpis-grasp play`` / ``bag_player``: returns 0 on success, 2 on bad arguments, 1 on errors."""
    from rclpy.utilities import remove_ros_args

    full = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    try:
        args = parser.parse_args(remove_ros_args(['gpis-grasp-play'] + full)[1:])
        remap = _parse_remap(args.remap)
        if not Path(args.bag).exists():
            raise ValueError(f'bag {args.bag} does not exist')
    except SystemExit as done:
        return int(done.code or 0)
    except ValueError as err:
        print(f'gpis-grasp play: error: {err}', file=sys.stderr)
        return 2

    rclpy.init(args=full)
    node: Node | None = None
    player: BagPlayer | None = None
    status = 0
    try:
        node = rclpy.create_node('bag_player')
        player = BagPlayer(node, args.bag, rate=args.rate, loop=args.loop, topics=args.topics, remap=remap,
                           reliable=args.reliable, wait_for_subscribers=args.wait_for_subscribers, clock=args.clock,
                           require=args.require)
        player.play(blocking=False)
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        announced = False
        while rclpy.ok() and (args.keep_alive or not player.done.is_set()):
            executor.spin_once(timeout_sec=0.1)
            if args.keep_alive and player.done.is_set() and not announced:
                announced = True
                node.get_logger().info(f'played {sum(player.counts.values())} messages; keeping the latched '
                                       'topics alive (Ctrl-C to quit)')
        if player.error is not None:
            status = 1
        else:
            total = sum(player.counts.values())
            per_topic = ', '.join(f'{t} {n}' for t, n in sorted(player.counts.items()))
            node.get_logger().info(f'played {total} messages from {args.bag} ({player.passes} pass(es)): {per_topic}')
            print(f'played {total} messages ({player.passes} pass(es)): {per_topic}')
    except ValueError as err:
        print(f'gpis-grasp play: error: {err}', file=sys.stderr)
        status = 2
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if player is not None:
            player.stop()
            player.destroy()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return status


if __name__ == '__main__':
    sys.exit(main())
