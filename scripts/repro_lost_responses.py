"""Minimal reproduction: service responses lost to a new client under CPU load (rmw_fastrtps).

One server process (std_srvs/Trigger, answers after ``--work`` s of CPU work in its callback) and
``--clients`` client processes started at the same moment; each calls ``--calls`` times at once
right after ``wait_for_service`` returned true and counts the answers that arrive within
``--timeout`` s. ``--hogs`` extra processes spin the CPU meanwhile (discovery lags). Prints the
answered count per client and the server's count of requests taken and answers sent (with the
RuntimeWarning rclpy issues when rmw_send_response times out). ``--client-depth 10`` gives the clients
rclpy's default history: every client receives every answer, and one that falls 10 behind loses its own
(scripts/repro_shared_response_history.py shows that alone). Loopback only, own domain.

    python scripts/repro_lost_responses.py --clients 5 --calls 20 --hogs 2
    python scripts/repro_lost_responses.py --clients 10 --calls 10 --hogs 3 --client-depth 10
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import sys
import time
import warnings


def _burn(seconds: float) -> None:
    end = time.monotonic() + seconds
    x = 0
    while time.monotonic() < end:
        x += 1


def _qos(depth: int | None = None):
    """The nodes' deep service history (a burst is not overwritten in the DDS queues), or ``depth``."""
    from gpis_grasp_ros.ros.nodes.common import SERVICE_QOS
    if depth is None:
        return SERVICE_QOS
    from rclpy.qos import QoSProfile
    return QoSProfile(depth=depth, history=SERVICE_QOS.history, reliability=SERVICE_QOS.reliability,
                      durability=SERVICE_QOS.durability)


def server(ready, stop, work: float, counts) -> None:
    import rclpy
    from rclpy.executors import MultiThreadedExecutor
    from std_srvs.srv import Trigger

    rclpy.init()
    node = rclpy.create_node('repro_server')
    warned = []

    def on_call(_req, res):
        _burn(work)
        counts[0] += 1
        res.success = True
        res.message = 'ok'
        return res

    srv = node.create_service(Trigger, 'repro', on_call, qos_profile=_qos())
    original = srv.send_response

    def send_response(response, header):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter('always')
            original(response, header)
        counts[1] += 1
        if caught:
            counts[2] += 1
            warned.append(str(caught[0].message))
    srv.send_response = send_response
    ex = MultiThreadedExecutor(num_threads=2)
    ex.add_node(node)
    ready.set()
    while not stop.is_set():
        ex.spin_once(timeout_sec=0.1)
    if warned:
        print(f'server: first send_response warning: {warned[0]}', file=sys.stderr)
    node.destroy_node()
    rclpy.try_shutdown()


def client(index: int, go, calls: int, timeout: float, out, depth: int | None) -> None:
    import rclpy
    from std_srvs.srv import Trigger

    rclpy.init()
    node = rclpy.create_node(f'repro_client_{index}')
    cli = node.create_client(Trigger, 'repro', qos_profile=_qos(depth))
    go.wait()
    if not cli.wait_for_service(timeout_sec=30.0):
        out.put((index, -1))
        return
    futures = [cli.call_async(Trigger.Request()) for _ in range(calls)]
    end = time.monotonic() + timeout
    while time.monotonic() < end and not all(f.done() for f in futures):
        rclpy.spin_once(node, timeout_sec=0.05)
    out.put((index, sum(f.done() for f in futures)))
    node.destroy_node()
    rclpy.try_shutdown()


def hog(stop) -> None:
    while not stop.is_set():
        _burn(0.05)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    p.add_argument('--clients', type=int, default=5)
    p.add_argument('--calls', type=int, default=20)
    p.add_argument('--work', type=float, default=0.02, help='CPU seconds per call in the server')
    p.add_argument('--hogs', type=int, default=2, help='CPU-burning processes')
    p.add_argument('--timeout', type=float, default=30.0)
    p.add_argument('--client-depth', type=int, default=None,
                   help="the clients' response history (default: the nodes' SERVICE_QOS; rclpy's default is 10)")
    p.add_argument('--domain', type=int, default=77)
    a = p.parse_args(argv)
    os.environ['ROS_DOMAIN_ID'] = str(a.domain)
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    ctx = mp.get_context('spawn')
    ready, stop, go = ctx.Event(), ctx.Event(), ctx.Event()
    counts = ctx.Array('i', 3)
    out = ctx.Queue()
    hogs = [ctx.Process(target=hog, args=(stop,)) for _ in range(a.hogs)]
    for h in hogs:
        h.start()
    srv = ctx.Process(target=server, args=(ready, stop, a.work, counts))
    srv.start()
    ready.wait(60)
    clients = [ctx.Process(target=client, args=(i, go, a.calls, a.timeout, out, a.client_depth))
               for i in range(a.clients)]
    for c in clients:
        c.start()
    time.sleep(2.0)  # every client process is up (imports done) and waits for the signal
    go.set()
    answered = dict(out.get(timeout=a.timeout + 60) for _ in clients)
    for c in clients:
        c.join(10)
    stop.set()
    srv.join(10)
    for h in hogs:
        h.join(5)
    total = sum(max(v, 0) for v in answered.values())
    print(f'answered per client: {[answered[i] for i in range(a.clients)]}')
    print(f'answered {total}/{a.clients * a.calls}; server took {counts[0]}, sent {counts[1]}, '
          f'send_response timeouts {counts[2]}')
    return 0 if total == a.clients * a.calls else 1


if __name__ == '__main__':
    sys.exit(main())
