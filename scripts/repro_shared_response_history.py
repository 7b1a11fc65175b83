"""Minimal reproduction: a plain rclpy client loses its answer to the answers sent to *other* clients.

rmw_fastrtps gives every client of a service its own response reader on the service's one response topic,
and the service's response writer sends each answer to all of them; the rmw drops, at take time, the
samples addressed to another client. Each reader keeps the client's QoS history: KEEP_LAST with depth 10
by default (``rclpy.qos.qos_profile_services_default``). So when more than ``depth`` answers to anyone
arrive before a client takes its own, the reader has already discarded it and that call is never answered
- no error, no warning, on either side.

Here: client B sends one call, client A ``--calls`` calls (std_srvs/SetBool). The server (its own
process) takes all the requests, answers B first and then A, and only then are the clients spun. With
A's calls >= B's depth, B's answer is gone; with ``--depth`` above A's calls it arrives. No project code;
loopback only, bounded (``--timeout``).

    python scripts/repro_shared_response_history.py                 # depth 10, A 10 calls: B never answered
    python scripts/repro_shared_response_history.py --depth 11      # every call answered
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import sys
import time


def server(expected: int, sent, timeout: float) -> None:
    """Take ``expected`` requests, then answer B's (data=True) first and A's after it."""
    import rclpy
    from rclpy.qos import HistoryPolicy, QoSProfile
    from std_srvs.srv import SetBool

    rclpy.init()
    node = rclpy.create_node('repro_history_server')
    # the service keeps every request of the burst (its own depth is not what this shows)
    srv = node.create_service(SetBool, 'repro_history', lambda _req, res: res,
                              qos_profile=QoSProfile(depth=1000, history=HistoryPolicy.KEEP_LAST))
    taken = []
    end = time.monotonic() + timeout
    while len(taken) < expected and time.monotonic() < end:
        request, header = srv.handle.service_take_request(SetBool.Request)
        if header is None:
            time.sleep(0.005)
            continue
        taken.append((request, header))
    taken.sort(key=lambda rh: not rh[0].data)  # B's request first
    for request, header in taken:
        srv.send_response(SetBool.Response(success=True, message='B' if request.data else 'A'), header)
        sent.value += 1
    time.sleep(1.0)  # keep the writer alive while the answers are acknowledged
    node.destroy_node()
    rclpy.try_shutdown()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    p.add_argument('--calls', type=int, default=10, help="client A's calls")
    p.add_argument('--depth', type=int, default=10, help="both clients' KEEP_LAST response depth (rclpy's default)")
    p.add_argument('--timeout', type=float, default=20.0)
    p.add_argument('--domain', type=int, default=None)
    a = p.parse_args(argv)
    if a.domain is not None:
        os.environ['ROS_DOMAIN_ID'] = str(a.domain)
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')

    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    from std_srvs.srv import SetBool

    rclpy.init()
    node = rclpy.create_node('repro_history_clients')
    # rclpy's default service QoS (qos_profile_services_default) with the depth asked for
    qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=a.depth, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.VOLATILE)
    client_a = node.create_client(SetBool, 'repro_history', qos_profile=qos)
    client_b = node.create_client(SetBool, 'repro_history', qos_profile=qos)

    ctx = mp.get_context('spawn')
    sent = ctx.Value('i', 0)
    srv = ctx.Process(target=server, args=(a.calls + 1, sent, a.timeout))
    srv.start()
    for c in (client_a, client_b):
        if not c.wait_for_service(timeout_sec=a.timeout):
            print('error: the server did not come up', file=sys.stderr)
            return 2
    time.sleep(0.5)  # the server's response writer has matched both readers (no discovery race here)
    b = client_b.call_async(SetBool.Request(data=True))
    futures_a = [client_a.call_async(SetBool.Request(data=False)) for _ in range(a.calls)]
    end = time.monotonic() + a.timeout
    while sent.value < a.calls + 1 and time.monotonic() < end:
        time.sleep(0.01)  # the clients are not spun while the answers arrive
    time.sleep(0.5)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    end = time.monotonic() + 3.0
    while time.monotonic() < end and not (b.done() and all(f.done() for f in futures_a)):
        executor.spin_once(timeout_sec=0.05)
    answered_a = sum(f.done() for f in futures_a)
    print(f'response depth {a.depth}: server sent {sent.value} answers (B first); '
          f'client A answered {answered_a}/{a.calls}, client B answered {int(b.done())}/1')
    srv.join(10)
    executor.shutdown()
    node.destroy_node()
    rclpy.try_shutdown()
    return 0 if b.done() and answered_a == a.calls else 1


if __name__ == '__main__':
    sys.exit(main())
