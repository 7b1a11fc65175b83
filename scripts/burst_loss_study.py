"""Study: which plain-client answers of a burst to planner_node are lost, and where.

planner_node in-process (as in test/ros/test_nodes_reliability.py's burst test: ``max_queue`` 128,
``num_grasp_samples`` 50, a harness executor of 48 threads), a probe node with ``--clients`` plain rclpy
clients and ``--calls`` seeded GP-M calls each (the same seeds across clients, so callers join one plan),
repeated ``--reps`` times with new seeds. Per call it records whether planner_node took the request and
sent the answer (and from which thread), and on the client side every take of the executor: answers taken
for this client, samples taken and dropped by the rmw as addressed to another client of the service, and
whether rclpy found the future. A call not answered within ``--timeout`` s is printed with that record.

    python scripts/burst_loss_study.py --reps 30 --client-depth 10      # rclpy's default client QoS
    python scripts/burst_loss_study.py --reps 30 --client-depth 1000    # the nodes' SERVICE_QOS depth
"""

from __future__ import annotations

import argparse
import collections
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / 'test')]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    p.add_argument('--reps', type=int, default=10)
    p.add_argument('--clients', type=int, default=4)
    p.add_argument('--calls', type=int, default=10, help='seeded calls per client and repetition')
    p.add_argument('--client-depth', type=int, default=10, help="the clients' KEEP_LAST depth (rclpy's default: 10)")
    p.add_argument('--callback-group', choices=('default', 'reentrant'), default='default',
                   help="the clients' callback group (the probe's default group is mutually exclusive)")
    p.add_argument('--fresh', action='store_true',
                   help='new clients for each repetition, calling right after wait_for_service (as the test)')
    p.add_argument('--timeout', type=float, default=30.0, help='s a repetition waits for its answers')
    p.add_argument('--hogs', type=int, default=0, help='CPU-burning processes during the run')
    p.add_argument('--domain', type=int, default=None)
    a = p.parse_args(argv)
    if a.domain is not None:
        os.environ['ROS_DOMAIN_ID'] = str(a.domain)
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    # CPU-burning processes; each ends after 30 min or when this process is gone
    hog = ('import os, time\nparent, end = os.getppid(), time.monotonic() + 1800\n'
           'while time.monotonic() < end and os.getppid() == parent:\n    t = time.monotonic() + 1\n'
           '    while time.monotonic() < t: pass\n')
    hogs = [subprocess.Popen([sys.executable, '-c', hog], stdout=subprocess.DEVNULL) for _ in range(a.hogs)]
    try:
        return _study(a)
    finally:
        for h in hogs:
            h.kill()


def _study(a: argparse.Namespace) -> int:
    from rclpy.callback_groups import ReentrantCallbackGroup
    from rclpy.executors import Executor
    from rclpy.parameter import Parameter
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    from gpis_grasp_interfaces.msg import GpisModel
    from gpis_grasp_interfaces.srv import GraspPlan
    from gpis_grasp_ros.data import messages
    from gpis_grasp_ros.data.bags import load_bag, posterior_from_scene
    from gpis_grasp_ros.ros import conversions
    from gpis_grasp_ros.ros.nodes.common import LATCHED_QOS
    from gpis_grasp_ros.ros.nodes.planner_node import PlannerNode
    from support.rosutil import RosHarness, wait_for

    # ---------------------------------------------------------------- client-side record of every take
    takes: dict[int, collections.Counter] = collections.defaultdict(collections.Counter)  # per client, this rep
    all_takes: collections.Counter = collections.Counter()
    original_take = Executor._take_client

    def take_client(self, client):
        execute = original_take(self, client)
        if execute is None:
            return None

        async def recorded():
            # the closure holds (header, response); header None = the rmw dropped a sample for another client
            header, _ = next(c.cell_contents for c in execute.__closure__ if isinstance(c.cell_contents, tuple))
            if header is None:
                takes[id(client)]['dropped'] += 1
                all_takes['dropped as another client\'s'] += 1
            else:
                with client._lock:
                    found = header.request_id.sequence_number in client._pending_requests
                what = 'own answer' if found else 'own answer, no future'
                takes[id(client)][what] += 1
                all_takes[what] += 1
            await execute()
        return recorded
    Executor._take_client = take_client

    bag = next((ROOT / 'bags').glob('H_*.mcap'))
    post, _ = posterior_from_scene(load_bag(bag))
    factory = conversions.RclpyFactory()
    model = messages.posterior_to_gpis_model(post, messages.header(factory, 1, 'camera_rgb_optical_frame'), factory)

    ros = RosHarness(threads=48)
    planner = ros.add(PlannerNode(context=ros.context, parameter_overrides=[
        Parameter('num_shape_samples', value=100), Parameter('num_initial_grasps', value=3),
        Parameter('max_queue', value=128), Parameter('num_grasp_samples', value=50)]))
    probe = ros.node('probe')
    pub = probe.create_publisher(GpisModel, 'gpis/model', LATCHED_QOS)
    pub.publish(model)
    assert wait_for(planner.has_model, 30.0), 'no model at planner_node'

    # ---------------------------------------------------------------- service introspection (rcl's events)
    from rclpy.service_introspection import ServiceIntrospectionState
    from service_msgs.msg import ServiceEventInfo as Info
    events_qos = QoSProfile(depth=100000, history=HistoryPolicy.KEEP_LAST,
                            reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
    events: dict[tuple[int, bytes, int], list[float]] = collections.defaultdict(list)  # (type, gid, seq) -> stamps

    events_lock = threading.Lock()

    def on_event(msg):
        i = msg.info
        with events_lock:
            events[(i.event_type, bytes(i.client_gid), i.sequence_number)].append(i.stamp.sec + 1e-9 * i.stamp.nanosec)
    listener = ros.node('introspection_listener')
    event_sub = listener.create_subscription(GraspPlan.Event, 'plan_grasp/_service_event', on_event, events_qos)
    service = planner.plan_service
    service.service.configure_introspection(planner.get_clock(), events_qos, ServiceIntrospectionState.METADATA)
    # which thread sent each answer: (seq, time before, time after, thread) around rclpy's send_response
    sends: list[tuple[int, float, float, str]] = []
    send = service._send

    def on_send(response, header):
        t0 = time.time()
        send(response, header)
        sends.append((header.request_id.sequence_number, t0, time.time(), threading.current_thread().name))
    service._send = on_send

    qos = QoSProfile(depth=a.client_depth, history=HistoryPolicy.KEEP_LAST,
                     reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
    group = ReentrantCallbackGroup() if a.callback_group == 'reentrant' else None

    def make_clients() -> list:
        made = [probe.create_client(GraspPlan, 'plan_grasp', qos_profile=qos, callback_group=group)
                for _ in range(a.clients)]
        for c in made:
            c.configure_introspection(probe.get_clock(), events_qos, ServiceIntrospectionState.METADATA)
        for c in made:
            assert c.wait_for_service(timeout_sec=10.0)
        # the clients' event publishers matched (their first events would be lost otherwise)
        assert wait_for(lambda: event_sub.get_publisher_count() == 1 + len(made), 20.0), 'introspection not matched'
        return made

    def gids_of(made: list, first_seq: int) -> dict:
        """Each client's gid in its own events: the clients sent their first call in list order."""
        assert wait_for(lambda: sum(k[0] == Info.REQUEST_SENT and k[2] == first_seq and k[1] not in old_gids
                                    for k in snapshot()) >= len(made), 10.0)
        firsts = sorted((min(v), k[1]) for k, v in snapshot().items()
                        if k[0] == Info.REQUEST_SENT and k[2] == first_seq and k[1] not in old_gids)
        return {i: g for i, (_, g) in enumerate(firsts)}

    old_gids: set[bytes] = set()
    clients = make_clients()
    gid: dict[int, bytes] = {}
    def server_gid(g: bytes) -> bytes:
        """planner_node's events name a caller by its response reader, the client's by its request writer
        (of one client: the same participant prefix; rmw_fastrtps makes the reader, then the writer)."""
        return g[:12] + (int.from_bytes(g[12:15], 'big') - 1).to_bytes(3, 'big') + b'\x04'

    def snapshot() -> dict:
        with events_lock:
            return {k: list(v) for k, v in events.items()}

    def record(i: int, seq: int) -> str:
        g = gid[i]
        sg = server_gid(g)
        events = snapshot()
        sent_at = events.get((Info.RESPONSE_SENT, sg, seq), [])
        threads = [t for stamp in sent_at for s, t0, t1, t in sends if s == seq and t0 - 0.01 <= stamp <= t1 + 0.01]
        return (f'request sent {len(events.get((Info.REQUEST_SENT, g, seq), []))}x, taken by planner '
                f'{len(events.get((Info.REQUEST_RECEIVED, sg, seq), []))}x, answer sent {len(sent_at)}x '
                f'(threads {sorted(set(threads))}), taken by the client '
                f'{len(events.get((Info.RESPONSE_RECEIVED, g, seq), []))}x')

    lost_reps, lost_calls = 0, 0
    t_all = time.monotonic()
    for rep in range(a.reps):
        if a.fresh and rep:
            old_gids |= set(gid.values())
            for c in clients:
                probe.destroy_client(c)
            clients = make_clients()
        calls = [(i, c, GraspPlan.Request(method='gp-m', seed=1 + k + 1000 * rep))
                 for k in range(a.calls) for i, c in enumerate(clients)]
        futures = []
        for i, c, req in calls:
            f = c.call_async(req)
            with c._lock:
                seq = next(s for s, g in c._pending_requests.items() if g is f)
            futures.append((i, seq, f))
        takes.clear()
        n_sent = len(sends)
        if a.fresh or rep == 0:
            gid = gids_of(clients, futures[0][1])
            if rep == 0:
                print('gids (client events -> planner_node events):',
                      {i: (g.hex(), server_gid(g).hex()) for i, g in gid.items()})
        t0 = time.monotonic()
        done = wait_for(lambda fs=futures: all(f.done() for _, _, f in fs), a.timeout)
        took = time.monotonic() - t0
        missing = [(i, seq, f) for i, seq, f in futures if not f.done()]
        line = f'rep {rep + 1:2d}: {len(futures) - len(missing)}/{len(futures)} answered in {took:.1f} s'
        print(line + ('' if done else '  LOST:'), flush=True)
        for i, seq, f in missing:
            with clients[i]._lock:
                pending = clients[i]._pending_requests.get(seq) is f
            print(f'    client {i} seq {seq}: {record(i, seq)}; future pending {pending}', flush=True)
        if missing:
            time.sleep(1.0)  # late takes
            written = len(sends) - n_sent
            print('    samples each client took of the', written, 'answers written to the service\'s readers '
                  '(its own + dropped as another\'s):', [sum(takes[id(c)].values()) for c in clients], flush=True)
        lost_reps += bool(missing)
        lost_calls += len(missing)
    print(f'client takes over all repetitions: {dict(all_takes)}')
    by_thread = collections.Counter(t.rstrip('0123456789_') for _, _, _, t in sends)
    print(f'answers sent, by thread: {dict(by_thread)}')
    print(f'summary: client depth {a.client_depth}, group {a.callback_group}: {lost_reps} of {a.reps} repetitions '
          f'lost {lost_calls} of {a.reps * len(clients) * a.calls} calls; '
          f'{time.monotonic() - t_all:.0f} s; load {os.getloadavg()[0]:.1f}')
    Executor._take_client = original_take
    ros.close()
    return 0 if lost_calls == 0 else 1


if __name__ == '__main__':
    sys.exit(main())
